"""``omnire bench waymo-read``: does reading a large Waymo segment stay flat in memory?

Generates a segment of the requested size (default 1 GB, ~250 frames of ~4 MB like a real
one: five JPEG cameras, TOP and four side LiDARs with two returns and the TOP pixel poses,
~60 labelled boxes), then reads it with the ``waymo`` dataparser in a fresh subprocess and
reports that process's peak resident memory above its state after the imports, next to
the size of what the reader returns (LiDAR points, poses). A reader that held the file
would grow by the file size; a streaming one grows by its output plus a few frames.

    omnire bench waymo-read                     # 1 GB in a temporary folder
    omnire bench waymo-read --size-mb 300 --keep --workdir /tmp/wbench
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

FRAME_CAMERAS = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT")
SIDE_LIDARS = ("FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR")


def _noise_jpeg(width: int, height: int, seed: int, quality: int = 90) -> bytes:
    import OpenImageIO as oiio

    rng = np.random.default_rng(seed)
    # Smoothed noise: JPEG sizes like camera images (~0.5 MB at 960x640), not pathological.
    img = rng.integers(0, 256, (height // 4, width // 4, 3), dtype=np.uint8).repeat(4, 0).repeat(4, 1)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "x.jpg")
        out = oiio.ImageOutput.create(path)
        spec = oiio.ImageSpec(width, height, 3, oiio.UINT8)
        spec.attribute("Compression", f"jpeg:{quality}")
        out.open(path, spec)
        out.write_image(np.ascontiguousarray(img))
        out.close()
        return Path(path).read_bytes()


def generate_segment(path: Path, size_bytes: int, seed: int = 0, image_size: tuple[int, int] = (960, 640)) -> dict:
    """Write a Waymo-like segment of about ``size_bytes`` to ``path`` (streamed: one frame
    at a time). Returns {"frames", "bytes"}. Payload blobs (JPEGs, compressed range images)
    are made once and repeated; poses, times and boxes change per frame."""
    from omnire_waymo.rangeimage import encode_matrix_float
    from omnire_waymo.tfrecord import TFRecordWriter
    from omnire_waymo.wod import dataset_pb2, label_pb2

    rng = np.random.default_rng(seed)
    W_img, H_img = image_size
    jpegs = {c: _noise_jpeg(W_img, H_img, seed + i) for i, c in enumerate(FRAME_CAMERAS)}

    def range_image(h: int, w: int, fill: float) -> bytes:
        # Ranges smooth along a row and quantised like a sensor's (compress as real ones do).
        img = np.full((h, w, 4), -1.0, np.float32)
        hit = rng.random((h, w)) < fill
        base = np.linspace(75.0, 3.0, h)[:, None] * (1 + 0.05 * rng.standard_normal((h, w)))
        img[hit, 0] = np.round(base[hit] * 64) / 64
        img[hit, 1] = np.round(rng.random(hit.sum()) * 256) / 256
        img[hit, 2] = 0.0
        return encode_matrix_float(img, level=1)

    # Real segments: the TOP LiDAR returns for most pixels, second returns and the short-range
    # side LiDARs for few.
    top = [range_image(64, 2650, 0.75), range_image(64, 2650, 0.1)]
    side = {n: [range_image(200, 600, 0.1), range_image(200, 600, 0.02)] for n in SIDE_LIDARS}
    pose_img = np.zeros((64, 2650, 6), np.float32)

    ctx = dataset_pb2.Context(name=f"omnire_bench_{seed}")
    for i, c in enumerate(FRAME_CAMERAS):
        cal = ctx.camera_calibrations.add()
        cal.name = dataset_pb2.CameraName.Name.Value(c)
        cal.intrinsic.extend([0.9 * W_img, 0.9 * W_img, W_img / 2, H_img / 2, 0.03, -0.3, 0.001, 0.001, 0.0])
        yaw = [0.0, 0.8, -0.8, 1.6, -1.6][i]
        E = np.eye(4)
        E[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        E[:3, 3] = [1.5, 0.0, 2.1]
        cal.extrinsic.transform.extend(E.reshape(-1).tolist())
        cal.width, cal.height = W_img, H_img
        cal.rolling_shutter_direction = dataset_pb2.CameraCalibration.LEFT_TO_RIGHT
    for name in ("TOP",) + SIDE_LIDARS:
        cal = ctx.laser_calibrations.add()
        cal.name = dataset_pb2.LaserName.Name.Value(name)
        if name == "TOP":
            cal.beam_inclinations.extend(np.linspace(-0.31, 0.045, 64).tolist())
        cal.beam_inclination_min, cal.beam_inclination_max = (-0.31, 0.045) if name == "TOP" else (-1.57, 0.52)
        E = np.eye(4)
        E[:3, 3] = [1.4, 0.0, 2.2]
        cal.extrinsic.transform.extend(E.reshape(-1).tolist())
    boxes = rng.uniform([-40, -20, 0, 3.5, 1.8, 1.5, -3], [40, 20, 1, 5.0, 2.1, 2.0, 3], (60, 7))

    t0 = 1_600_000_000_000_000
    frames = 0
    with TFRecordWriter(path) as w:
        while w.bytes_written < size_bytes:
            x = 1.0 * frames  # 10 m/s at 10 Hz
            pose = np.eye(4)
            pose[:3, 3] = [x, 0.0, 0.0]
            f = dataset_pb2.Frame(context=ctx, timestamp_micros=t0 + 100_000 * frames)
            f.pose.transform.extend(pose.reshape(-1).tolist())
            for c in FRAME_CAMERAS:
                im = f.images.add()
                im.name = dataset_pb2.CameraName.Name.Value(c)
                im.image = jpegs[c]
                im.pose.transform.extend(pose.reshape(-1).tolist())
                im.velocity.v_x = 10.0
                ts = (t0 + 100_000 * frames) * 1e-6 + 0.05
                im.pose_timestamp, im.shutter = ts, 0.003
                im.camera_trigger_time, im.camera_readout_done_time = ts - 0.025, ts + 0.025
            pose_img[..., 3] = x
            laser = f.lasers.add()
            laser.name = dataset_pb2.LaserName.TOP
            laser.ri_return1.range_image_compressed = top[0]
            laser.ri_return2.range_image_compressed = top[1]
            laser.ri_return1.range_image_pose_compressed = encode_matrix_float(pose_img, level=1)
            for name in SIDE_LIDARS:
                laser = f.lasers.add()
                laser.name = dataset_pb2.LaserName.Name.Value(name)
                laser.ri_return1.range_image_compressed = side[name][0]
                laser.ri_return2.range_image_compressed = side[name][1]
            for k, b in enumerate(boxes):
                lab = f.laser_labels.add()
                lab.id = f"obj{k:03d}"
                lab.type = label_pb2.Label.TYPE_VEHICLE
                lab.box.center_x, lab.box.center_y, lab.box.center_z = b[0] + x, b[1], b[2]
                lab.box.length, lab.box.width, lab.box.height, lab.box.heading = b[3], b[4], b[5], b[6]
            w.write(f.SerializeToString())
            frames += 1
    return {"frames": frames, "bytes": path.stat().st_size}


def read_and_measure(path: Path, image_dir: Path, load_lidar: bool, max_points: int) -> dict:
    """In this process: parse ``path`` and report memory (run it in a fresh process)."""
    from omnire.command_api import process_status_kib
    from omnire_waymo.dataparser import WaymoConfig
    import google.protobuf.message  # noqa: F401

    base = process_status_kib("VmRSS")
    t = time.perf_counter()
    scene = WaymoConfig(data=path, image_dir=image_dir, cameras=FRAME_CAMERAS, load_lidar=load_lidar,
                        max_lidar_points_per_frame=max_points).setup().parse()
    seconds = time.perf_counter() - t
    peak = process_status_kib("VmHWM")
    retained = sum(p.nbytes for p in (scene.lidar.points if scene.lidar else []) if p is not None)
    retained += sum(c.cam_to_world.nbytes + sum(v.nbytes for v in c.extras.values()) for c in scene.cameras)
    retained += sum(tr.poses.nbytes + sum(getattr(v, "nbytes", 0) for v in tr.extras.values()) for tr in scene.tracks)
    return {"frames": scene.num_frames, "seconds": seconds, "baseline_mb": base / 1024,
            "peak_growth_mb": (peak - base) / 1024, "retained_mb": retained / 2**20,
            "lidar_points": int(sum(len(p) for p in scene.lidar.points if p is not None)) if scene.lidar else 0}


def measure_in_subprocess(path: Path, image_dir: Path, load_lidar: bool, max_points: int) -> dict:
    cmd = [sys.executable, "-m", "omnire_waymo.bench", "--measure", str(path), "--image-dir", str(image_dir),
           "--max-points", str(max_points)] + ([] if load_lidar else ["--no-lidar"])
    env = dict(os.environ, OMP_NUM_THREADS="1")
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"reader subprocess failed ({res.returncode}):\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv: list[str], plugins=None) -> int:
    p = argparse.ArgumentParser(prog="omnire bench waymo-read", description=__doc__.splitlines()[0])
    p.add_argument("--size-mb", type=float, default=1024.0, help="size of the generated segment (MiB)")
    p.add_argument("--workdir", type=Path, default=None, help="folder for the segment and extracted images (default: a temporary one)")
    p.add_argument("--keep", action="store_true", help="keep the generated segment (reused by the next run with the same size)")
    p.add_argument("--max-points", type=int, default=20000, help="LiDAR points kept per frame in the LiDAR run (0 = all)")
    a = p.parse_args(argv)

    from rich.console import Console
    from rich.table import Table

    console = Console()
    tmp = None
    if a.workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="omnire-waymo-bench-")
        work = Path(tmp.name)
    else:
        work = a.workdir
        work.mkdir(parents=True, exist_ok=True)
    try:
        seg = work / f"bench_{int(a.size_mb)}MB.tfrecord"
        if seg.is_file() and seg.stat().st_size >= a.size_mb * 2**20:
            console.print(f"reusing {seg} ({seg.stat().st_size / 2**20:.0f} MiB)")
        else:
            t = time.perf_counter()
            info = generate_segment(seg, int(a.size_mb * 2**20))
            console.print(f"generated {seg}: {info['frames']} frames, {info['bytes'] / 2**20:.0f} MiB "
                          f"in {time.perf_counter() - t:.1f} s")
        size_mb = seg.stat().st_size / 2**20
        table = Table(title=f"waymo reader on a {size_mb:.0f} MiB segment (fresh process per run)")
        for col in ("run", "frames", "read s", "peak RSS growth MiB", "output MiB", "growth - output MiB", "points"):
            table.add_column(col, justify="right")
        results = {}
        for label, lidar in (("cameras + labels", False), (f"+ LiDAR ({a.max_points}/frame)", True)):
            r = measure_in_subprocess(seg, work / "images", lidar, a.max_points)
            results[label] = r
            table.add_row(label, str(r["frames"]), f"{r['seconds']:.1f}", f"{r['peak_growth_mb']:.0f}",
                          f"{r['retained_mb']:.0f}", f"{r['peak_growth_mb'] - r['retained_mb']:.0f}", str(r["lidar_points"]))
        console.print(table)
        console.print(json.dumps({"file_mb": size_mb, **results}))
        if not a.keep:
            seg.unlink(missing_ok=True)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return 0


def _measure_cli() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--measure", type=Path, required=True)
    p.add_argument("--image-dir", type=Path, required=True)
    p.add_argument("--max-points", type=int, default=0)
    p.add_argument("--no-lidar", action="store_true")
    a = p.parse_args()
    print(json.dumps(read_and_measure(a.measure, a.image_dir, not a.no_lidar, a.max_points)))


if __name__ == "__main__":
    _measure_cli()
