"""Scene writer ``argoverse2``: a synthetic scene (processed layout, ``omnire synth``) as an
AV2 sensor log, so the reader is tested on scenes whose every pose, box and point is known.

Written into ``output`` (one log directory), in AV2's column names and types::

    city_SE3_egovehicle.feather      int64 timestamp_ns, double qw qx qy qz tx_m ty_m tz_m; poses at every
                                     sweep and image time plus half-way between sweeps (AV2 logs hold
                                     poses at every sensor time, far denser than the sweeps)
    calibration/egovehicle_SE3_sensor.feather   string sensor_name, double pose columns (cameras, up_lidar)
    calibration/intrinsics.feather   string sensor_name, double fx_px fy_px cx_px cy_px k1 k2 k3,
                                     uint16 height_px width_px (pixel centres at integers, as AV2)
    annotations.feather              int64 timestamp_ns, string track_uuid (uuid5 of the synthetic id)
                                     and category, double sizes and pose (box -> ego at the sweep),
                                     int64 num_interior_pts (counted on the written sweep)
    sensors/lidar/<ns>.feather       halffloat x y z (ego frame, as AV2 stores them), uint8 intensity
                                     and laser_number (0: one synthetic LiDAR), int32 offset_ns (0)
    sensors/cameras/<ring camera>/<ns>.jpg       the synthetic images (bytes copied)

The city frame is the processed reader's world moved by :data:`CITY_FROM_WORLD` (a yaw and
a translation of kilometres, as AV2 city coordinates are), so the reader's own world
alignment is exercised. The ego frame is the generator's true ego frame (from
``ground_truth.npz``; the processed layout may store a LiDAR pose as its "ego"). Synthetic
camera k is written as the k-th of :data:`~omnire_argoverse2.log.RING_CAMERAS` with its
own extrinsics. Timestamps start at :data:`T0_NS`. Not written: masks, depth, SMPL poses
(AV2 has none), maps.
"""
from __future__ import annotations

import io
import uuid
import warnings
from pathlib import Path

import numpy as np

from omnire.api import (
    BYTE_INTENSITY, UserError, atomic_write_bytes, interpolate_poses, invert_se3, rot_z, rotmat_to_quat,
)
from omnire_argoverse2 import log as av2

T0_NS = 315_966_265_259_836_000
"""First sweep time of written logs (nanoseconds, the epoch of AV2's own timestamps)."""
CITY_FROM_WORLD = np.eye(4)
CITY_FROM_WORLD[:3, :3] = rot_z(np.array(0.6))
CITY_FROM_WORLD[:3, 3] = (2150.25, -830.5, 41.0)
"""(4, 4) processed world -> written city frame."""
WRITTEN_CATEGORY = {"vehicle": "REGULAR_VEHICLE", "human": "PEDESTRIAN", "cyclist": "BICYCLIST",
                    "other": "CONSTRUCTION_CONE"}
"""omnire category of a synthetic track -> the AV2 category written for it."""
_UUID_NAMESPACE = uuid.UUID("6f6d6e69-7265-2d61-7632-2d7472616b73")


def track_uuid(track_id: str) -> str:
    """The AV2 track_uuid written for a synthetic track id (deterministic)."""
    return str(uuid.uuid5(_UUID_NAMESPACE, track_id))


def _feather_bytes(columns: dict) -> bytes:
    """Arrow columns -> Feather v2 bytes (Arrow IPC file, as AV2 ships)."""
    import pyarrow as pa
    import pyarrow.feather as feather

    sink = io.BytesIO()
    feather.write_feather(pa.table(columns), sink)
    return sink.getvalue()


def _pose_columns(T: np.ndarray) -> dict:
    """(N, 4, 4) rigid transforms -> AV2 pose columns (unit wxyz with qw >= 0, metres)."""
    import pyarrow as pa

    q = rotmat_to_quat(T[:, :3, :3]) if len(T) else np.zeros((0, 4))
    q = q / np.linalg.norm(q, axis=1, keepdims=True) if len(T) else q
    cols = {k: pa.array(q[:, i], pa.float64()) for i, k in enumerate(("qw", "qx", "qy", "qz"))}
    cols.update({k: pa.array(T[:, i, 3], pa.float64()) for i, k in enumerate(("tx_m", "ty_m", "tz_m"))})
    return cols


def _constant(T: np.ndarray, what: str, tol: float = 1e-5) -> np.ndarray:
    """The common value of (F, 4, 4) transforms that must not change over the frames."""
    spread = float(np.abs(T - T[0]).max())
    if spread > tol:
        raise UserError(f"{what} changes over the frames by up to {spread:.3g}; AV2 stores one fixed "
                        "calibration per sensor")
    return T[0]


def write_scene(source: Path, output: Path) -> None:
    """Write the synthetic scene in ``source`` (processed layout with ground_truth.npz) as an
    AV2 sensor log into the empty folder ``output`` (see the module docstring)."""
    import pyarrow as pa

    from omnire_processed.reader import ProcessedDataparser, ProcessedDataparserConfig

    source, output = Path(source), Path(output)
    if not output.is_dir() or any(output.iterdir()):
        raise UserError(f"{output}: the argoverse2 writer needs an existing empty folder")
    parser = ProcessedDataparser(ProcessedDataparserConfig(data=source, scale=1.0, holdout_every=0,
                                                           load_human_poses=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the processed reader's notes concern its own conventions
        scene = parser.parse()
    if scene.lidar is None or scene.lidar.available_frames() != list(range(scene.num_frames)):
        raise UserError(f"{source}: every frame needs a LiDAR sweep (AV2 frames are the sweeps)")
    if len(scene.cameras) > len(av2.RING_CAMERAS):
        raise UserError(f"{source}: {len(scene.cameras)} cameras; AV2 has {len(av2.RING_CAMERAS)} ring cameras")

    # Ego poses (F, 4, 4) in the processed world: the true ego frame where ground truth says it.
    gt_path = source / "ground_truth.npz"
    if gt_path.is_file():
        with np.load(gt_path) as gt:
            ego = parser.world_from_file @ gt["file_from_generator"] @ gt["ego_to_world"][scene.source_frames]
    else:
        ego = scene.ego_poses
    city_ego = CITY_FROM_WORLD[None] @ ego
    frame_ns = T0_NS + np.round((scene.frame_timestamps - scene.frame_timestamps[0]) * 1e9).astype(np.int64)
    rel = lambda ns: (ns - T0_NS).astype(np.float64) * 1e-9  # noqa: E731 - seconds for interpolation

    # Calibration and images.
    sensor_names, sensor_poses, intr_rows, pose_ns = [], [], [], [frame_ns]
    for k, cam in enumerate(scene.cameras):
        name = av2.RING_CAMERAS[k]
        cam_ns = T0_NS + np.round((cam.timestamps - scene.frame_timestamps[0]) * 1e9).astype(np.int64)
        pose_ns.append(cam_ns)
        ego_at_cam = interpolate_poses(rel(frame_ns), ego, rel(cam_ns))
        sensor_names.append(name)
        sensor_poses.append(_constant(invert_se3(ego_at_cam) @ cam.cam_to_world, f"camera {cam.name} in the ego frame"))
        dist = np.zeros(5) if cam.distortion is None else np.asarray(cam.distortion, np.float64)
        if dist[2] or dist[3]:
            raise UserError(f"camera {cam.name}: tangential distortion p1 p2 {dist[2:4]} cannot be written in "
                            "AV2 (radial k1 k2 k3 only)")
        K = cam.intrinsics  # scale 1: the files' resolution, pixel centres at +0.5
        intr_rows.append((name, K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5, dist[0], dist[1], dist[4],
                          cam.height, cam.width))
        for ns, src in zip(cam_ns, cam.image_paths):
            dst = output / "sensors" / "cameras" / name / f"{int(ns)}.jpg"
            atomic_write_bytes(dst, src.read_bytes() if src.suffix.lower() in (".jpg", ".jpeg") else _jpeg_bytes(src))
    world_to_ego = invert_se3(ego)  # (F, 4, 4)
    origins = scene.lidar.origins  # (F, 3) world
    in_ego = np.einsum("fij,fj->fi", world_to_ego[:, :3, :3], origins) + world_to_ego[:, :3, 3]  # (F, 3)
    spread = float(np.abs(in_ego - in_ego[0]).max())
    if spread > 1e-4:
        raise UserError(f"{source}: the LiDAR origin moves in the ego frame by {spread:.3g} m; AV2 stores one "
                        "fixed LiDAR extrinsic")
    up = np.eye(4)
    up[:3, 3] = in_ego[0]
    sensor_names.append(av2.LIDAR_SENSOR)
    sensor_poses.append(up)

    calib = output / "calibration"
    atomic_write_bytes(calib / "egovehicle_SE3_sensor.feather", _feather_bytes(
        {"sensor_name": pa.array(sensor_names, pa.string()), **_pose_columns(np.stack(sensor_poses))}))
    cols = list(zip(*intr_rows))
    atomic_write_bytes(calib / "intrinsics.feather", _feather_bytes({
        "sensor_name": pa.array(cols[0], pa.string()),
        **{n: pa.array(np.asarray(cols[i], np.float64), pa.float64())
           for i, n in enumerate(("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3"), start=1)},
        "height_px": pa.array(np.asarray(cols[8]), pa.uint16()),
        "width_px": pa.array(np.asarray(cols[9]), pa.uint16()),
    }))

    # Ego poses at every sweep and image time and half-way between sweeps.
    mids = (frame_ns[:-1] + frame_ns[1:]) // 2
    all_ns = np.unique(np.concatenate(pose_ns + [mids]))
    atomic_write_bytes(output / "city_SE3_egovehicle.feather", _feather_bytes({
        "timestamp_ns": pa.array(all_ns, pa.int64()),
        **_pose_columns(interpolate_poses(rel(frame_ns), city_ego, rel(all_ns))),
    }))

    # Sweeps (ego frame, float16 as AV2) and the cuboids counted on them.
    unit = scene.lidar.intensity  # in [0, 1]: the processed reader maps its files' scale
    written_pts = []
    for f, (ns, pts) in enumerate(zip(frame_ns, scene.lidar.points)):
        M = world_to_ego[f]
        p = (pts.astype(np.float64) @ M[:3, :3].T + M[:3, 3]).astype(np.float16)
        written_pts.append(p.astype(np.float64))
        n = len(p)
        atomic_write_bytes(output / "sensors" / "lidar" / f"{int(ns)}.feather", _feather_bytes({
            "x": pa.array(p[:, 0], pa.float16()), "y": pa.array(p[:, 1], pa.float16()),
            "z": pa.array(p[:, 2], pa.float16()),
            "intensity": pa.array(np.zeros(n, np.uint8) if unit is None
                                  else np.round(BYTE_INTENSITY.from_unit(unit[f])).astype(np.uint8), pa.uint8()),
            "laser_number": pa.array(np.zeros(n, np.uint8), pa.uint8()),
            "offset_ns": pa.array(np.zeros(n, np.int32), pa.int32()),
        }))

    rows = []  # (timestamp_ns, uuid, category, size (3,), box->ego (4,4), num_interior_pts)
    for tr in scene.tracks:
        for f in tr.frames():
            box_ego = world_to_ego[f] @ tr.poses[f]
            n_in = int(av2.points_in_boxes(written_pts[f], box_ego[None], tr.size[None])[0])
            rows.append((int(frame_ns[f]), track_uuid(tr.track_id), WRITTEN_CATEGORY[tr.category], tr.size,
                         box_ego, n_in))
    rows.sort(key=lambda r: (r[0], r[1]))
    poses = np.stack([r[4] for r in rows]) if rows else np.zeros((0, 4, 4))
    sizes = np.stack([r[3] for r in rows]) if rows else np.zeros((0, 3))
    atomic_write_bytes(output / "annotations.feather", _feather_bytes({
        "timestamp_ns": pa.array([r[0] for r in rows], pa.int64()),
        "track_uuid": pa.array([r[1] for r in rows], pa.string()),
        "category": pa.array([r[2] for r in rows], pa.string()),
        "length_m": pa.array(sizes[:, 0], pa.float64()),
        "width_m": pa.array(sizes[:, 1], pa.float64()),
        "height_m": pa.array(sizes[:, 2], pa.float64()),
        **_pose_columns(poses),
        "num_interior_pts": pa.array([r[5] for r in rows], pa.int64()),
    }))


def _jpeg_bytes(src: Path) -> bytes:
    """An image file of another format re-encoded as JPEG."""
    import tempfile

    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(src))
    with tempfile.TemporaryDirectory() as tmp:
        dst = Path(tmp) / "image.jpg"
        if buf.has_error or not buf.write(str(dst), "uint8"):
            raise UserError(f"{src}: cannot re-encode as JPEG ({buf.geterror()})")
        return dst.read_bytes()
