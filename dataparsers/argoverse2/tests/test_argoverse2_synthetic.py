"""Round trip: a synthetic scene read by the processed reader vs the same scene written as an
AV2 log (pyarrow feather files, ring-camera jpgs) and read by the argoverse2 reader; camera
timing, error messages, and a real `omnire train` on the written log."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.feather as feather
import pytest

from omnire.api import ConfigError, SceneDataError, interpolate_poses
from omnire_argoverse2 import log as av2
from omnire_argoverse2.dataparser import Argoverse2Config, Argoverse2Dataparser
from omnire_argoverse2.writer import T0_NS, track_uuid

CAMS = ("ring_front_center", "ring_front_left", "ring_front_right")
REAL_LOG = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "av2" / "sensor" / "val" / \
    "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def read_av2(log: Path, **kw):
    kw.setdefault("cameras", CAMS)
    return Argoverse2Dataparser(Argoverse2Config(data=log, **kw)).parse()


def read_processed(scene: Path, **kw):
    from omnire_processed.reader import ProcessedDataparser, ProcessedDataparserConfig

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ProcessedDataparser(ProcessedDataparserConfig(data=scene, **kw)).parse()


def snapshot(folder: Path) -> dict:
    return {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def test_round_trip_against_the_processed_reader(synthetic_log):
    processed, log = synthetic_log
    before = snapshot(log)
    P = read_processed(processed, scale=1.0)
    A = read_av2(log, scale=1.0, max_track_gap=0.0)
    assert snapshot(log) == before  # nothing written into the dataset directory
    F = P.num_frames
    assert F == A.num_frames == 8 and [c.name for c in A.cameras] == list(CAMS)
    np.testing.assert_array_equal(A.source_frames, np.arange(F))
    # Time: frames and cameras on the same clock (AV2 ns since T0_NS).
    np.testing.assert_allclose(A.frame_timestamps - T0_NS * 1e-9, P.frame_timestamps - P.frame_timestamps[0], atol=1e-6)

    # The worlds differ by one rigid motion about z (origin at the true ego vs the file's pose).
    M = A.cameras[0].cam_to_world[0] @ np.linalg.inv(P.cameras[0].cam_to_world[0])  # P world -> A world
    np.testing.assert_allclose(M[2, :3], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(M[:3, 2], [0, 0, 1], atol=1e-9)
    for a, p in zip(A.cameras, P.cameras):
        assert (a.width, a.height) == (p.width, p.height) == (72, 48)
        np.testing.assert_allclose(a.intrinsics, p.intrinsics, atol=1e-9)
        np.testing.assert_allclose(a.cam_to_world, M[None] @ p.cam_to_world, atol=1e-6)
        np.testing.assert_allclose(a.timestamps - T0_NS * 1e-9, p.timestamps - P.frame_timestamps[0], atol=1e-6)
        np.testing.assert_array_equal(a.distortion, np.zeros(5))
        np.testing.assert_array_equal(a.extras["offset_from_sweep_s"], np.zeros(F))
        for ia, ip in zip(a.image_paths, p.image_paths):
            assert ia.read_bytes() == ip.read_bytes()

    # Ego poses: the generator's true ego frame, first one at the origin heading along +x.
    with np.load(processed / "ground_truth.npz") as gt:
        ego_true = gt["ego_to_world"]
    W = A.ego_poses @ np.linalg.inv(ego_true)  # generator world -> A world, one constant motion
    np.testing.assert_allclose(W, np.broadcast_to(W[0], W.shape), atol=1e-6)
    np.testing.assert_allclose(A.ego_poses[0][:3, 3], 0, atol=1e-9)
    np.testing.assert_allclose(A.ego_poses[0][:3, 0], [1, 0, 0], atol=1e-9)

    # Boxes: same tracks, presence, sizes, categories; poses up to M.
    by_uuid = {t.track_id: t for t in A.tracks}
    assert len(by_uuid) == len(P.tracks) > 5
    for p in P.tracks:
        a = by_uuid[track_uuid(p.track_id)]
        np.testing.assert_array_equal(a.present, p.present)
        assert a.category == p.category
        np.testing.assert_allclose(a.size, p.size, atol=1e-9)
        np.testing.assert_allclose(a.poses[a.present], M[None] @ p.poses[p.present], atol=1e-6)
        np.testing.assert_array_equal(a.extras["annotated"], p.present)
    assert {t.category for t in A.tracks} >= {"vehicle", "human", "cyclist"}

    # LiDAR: same points up to M, within the float16 rounding of AV2's ego-frame x y z
    # (half an ulp: 2^-11 of each coordinate; sqrt(3) of the largest for the 3-vector).
    for f in range(F):
        pa_, pp = A.lidar.points[f].astype(np.float64), P.lidar.points[f].astype(np.float64)
        assert pa_.shape == pp.shape and len(pp) > 10_000
        E = np.linalg.inv(A.ego_poses[f])
        ego_xyz = pa_ @ E[:3, :3].T + E[:3, 3]
        tol = np.sqrt(3) * 2.0 ** -11 * np.abs(ego_xyz).max(1) + 1e-4
        err = np.linalg.norm(pa_ - (pp @ M[:3, :3].T + M[:3, 3]), axis=1)
        assert (err <= tol).all(), float((err - tol).max())
        # Intensity: both in [0, 1], AV2's uint8 within half a step of the processed value.
        assert 0 <= A.lidar.intensity[f].min() and A.lidar.intensity[f].max() <= 1
        np.testing.assert_allclose(A.lidar.intensity[f], P.lidar.intensity[f], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(A.lidar.origins, P.lidar.origins @ M[:3, :3].T + M[:3, 3], atol=1e-6)

    # Written cuboid point counts agree with the written sweeps (the check done on real logs).
    ann = av2.read_annotations(log)
    ns, paths = av2.sweep_files(log)
    for t, path in zip(ns, paths):
        rows = ann.at(t)
        counts = av2.points_in_boxes(av2.read_sweep(path).xyz, ann.ego_SE3_box[rows], ann.size[rows])
        np.testing.assert_array_equal(counts, ann.num_interior_pts[rows])
    assert ann.num_interior_pts.sum() > 100


def test_scale_frame_range_and_default_cameras(synthetic_log):
    processed, log = synthetic_log
    P = read_processed(processed, scale=0.5, start_frame=2, end_frame=6)
    A = read_av2(log, scale=0.5, start_frame=2, end_frame=6, load_lidar=False)
    assert A.num_frames == 4 and A.lidar is None
    np.testing.assert_array_equal(A.source_frames, [2, 3, 4, 5])
    for a, p in zip(A.cameras, P.cameras):
        assert (a.width, a.height) == (p.width, p.height) == (36, 24)
        np.testing.assert_allclose(a.intrinsics, p.intrinsics, atol=1e-9)
    # Origin at the first *loaded* ego pose.
    np.testing.assert_allclose(A.ego_poses[0][:3, 3], 0, atol=1e-9)
    # Default: the seven ring cameras, of which this log has three (a warning names the others).
    with pytest.warns(UserWarning, match="ring_side_left"):
        D = Argoverse2Dataparser(Argoverse2Config(data=log, end_frame=2)).parse()
    assert [c.name for c in D.cameras] == list(CAMS)
    with pytest.raises(ConfigError, match="select nothing"):
        read_av2(log, start_frame=5, end_frame=20)


def _copy(log: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "log"
    shutil.copytree(log, dst)
    return dst


def test_nearest_image_per_sweep_with_its_own_time_and_pose(synthetic_log, tmp_path):
    """Images 12 ms after each sweep (plus decoys 40 ms after): the nearest is chosen, its
    exact time kept, and the camera posed with the ego pose interpolated to that time."""
    _, log = synthetic_log
    ref = read_av2(log, scale=1.0)
    log = _copy(log, tmp_path)
    folder = log / "sensors" / "cameras" / "ring_front_left"
    for p in sorted(folder.glob("*.jpg")):
        ns = int(p.stem)
        shutil.copyfile(p, folder / f"{ns + 40_000_000}.jpg")
        p.rename(folder / f"{ns + 12_000_000}.jpg")
    A = read_av2(log, scale=1.0)
    cam, cam0 = A.cameras[1], ref.cameras[1]
    np.testing.assert_allclose(cam.timestamps - A.frame_timestamps, 0.012, atol=1e-6)
    np.testing.assert_array_equal(cam.extras["offset_from_sweep_s"], np.full(A.num_frames, 0.012))
    assert [int(p.stem) for p in cam.image_paths] == list(cam.extras["timestamp_ns"])
    cam_to_ego = np.linalg.inv(ref.ego_poses[0]) @ cam0.cam_to_world[0]
    rel = A.frame_timestamps - A.frame_timestamps[0]
    ego_at = interpolate_poses(rel, A.ego_poses, cam.timestamps - A.frame_timestamps[0])
    np.testing.assert_allclose(cam.cam_to_world, ego_at @ cam_to_ego, atol=1e-7)
    moved = np.linalg.norm(cam.cam_to_world[:-1, :3, 3] - cam0.cam_to_world[:-1, :3, 3], axis=1)
    assert (moved > 0.05).all()  # the ego drives ~7 m/s: 12 ms is ~8 cm
    np.testing.assert_allclose(A.cameras[0].cam_to_world, ref.cameras[0].cam_to_world, atol=1e-9)


def test_missing_images_around_a_sweep(synthetic_log, tmp_path):
    log = _copy(synthetic_log[1], tmp_path)
    ns, _ = av2.sweep_files(log)
    (log / "sensors" / "cameras" / "ring_front_right" / f"{ns[3]}.jpg").unlink()
    with pytest.raises(SceneDataError, match=r"ring_front_right: the image nearest the sweep at timestamp_ns "
                                             rf"{ns[3]} is [+-]100.0 ms away .*--max-camera-offset"):
        read_av2(log)
    A = read_av2(log, max_camera_offset=0.15)
    assert abs(A.cameras[2].extras["offset_from_sweep_s"][3]) == pytest.approx(0.1)


def _rewrite(path: Path, change) -> None:
    table = feather.read_table(path)
    feather.write_feather(change(table), path)


def test_clear_errors_for_malformed_files(synthetic_log, tmp_path):
    log = _copy(synthetic_log[1], tmp_path)
    ann = log / "annotations.feather"
    ann.write_bytes(b"not arrow")
    with pytest.raises(SceneDataError, match=r"annotations.feather: not a readable Feather"):
        read_av2(log)
    shutil.copyfile(synthetic_log[1] / "annotations.feather", ann)

    poses = log / "city_SE3_egovehicle.feather"
    _rewrite(poses, lambda t: t.drop(["qw"]))
    with pytest.raises(SceneDataError, match=r"city_SE3_egovehicle.feather: ego poses .* lacks columns \['qw'\]"):
        read_av2(log)
    shutil.copyfile(synthetic_log[1] / "city_SE3_egovehicle.feather", poses)
    _rewrite(poses, lambda t: t.set_column(t.column_names.index("qw"), "qw", pa.array(np.zeros(len(t)))))
    with pytest.raises(SceneDataError, match=r"city_SE3_egovehicle.feather: row 0: quaternion"):
        read_av2(log)
    shutil.copyfile(synthetic_log[1] / "city_SE3_egovehicle.feather", poses)

    intr = log / "calibration" / "intrinsics.feather"
    _rewrite(intr, lambda t: t.filter(pc.not_equal(t["sensor_name"], "ring_front_left")))
    with pytest.raises(SceneDataError, match=r"intrinsics.feather: no row with sensor_name 'ring_front_left'"):
        read_av2(log)
    _rewrite(intr, lambda t: t.set_column(t.column_names.index("width_px"), "width_px",
                                          pa.array(np.full(len(t), 100, np.uint16))))
    with pytest.raises(SceneDataError, match=r"\.jpg: image is 72x48 but .*intrinsics.feather gives"):
        read_av2(log, cameras=("ring_front_center",))

    with pytest.raises(SceneDataError, match=r"sensors/cameras/ring_rear_left: missing camera folder"):
        read_av2(log, cameras=("ring_rear_left",))
    with pytest.raises(SceneDataError, match="not AV2 cameras"):
        read_av2(log, cameras=("front_camera",))
    (log / "sensors" / "lidar" / "12ab.feather").write_bytes(b"")
    with pytest.raises(SceneDataError, match=r"12ab.feather: file name must be <timestamp_ns>.feather"):
        read_av2(log)


def test_written_schema_matches_real_av2_files(synthetic_log):
    """Column names and Arrow types of every written table are those of real AV2 files."""
    if not REAL_LOG.is_dir():
        pytest.skip("real AV2 fixtures (../shared/data/av2) not present")
    _, log = synthetic_log
    pairs = [("annotations.feather",) * 2, ("city_SE3_egovehicle.feather",) * 2,
             ("calibration/intrinsics.feather",) * 2, ("calibration/egovehicle_SE3_sensor.feather",) * 2,
             (next((log / "sensors" / "lidar").glob("*.feather")),
              next((REAL_LOG / "sensors" / "lidar").glob("*.feather")))]
    for ours, real in pairs:
        a = feather.read_table(log / ours).schema
        b = feather.read_table(REAL_LOG / real).schema
        assert [(f.name, f.type) for f in a] == [(f.name, f.type) for f in b], ours


def test_train_three_steps_on_a_synthetic_av2_log(tmp_path):
    """`omnire synth --format argoverse2` (its entry function, in-process) then
    `omnire train 3dgs argoverse2` in a real subprocess."""
    from omnire.plugins import load_plugins
    from omnire_synthetic.cli import main as synth_main

    scene = tmp_path / "av2_scene"
    assert synth_main(["urban", str(scene), "--tiny", "--format", "argoverse2"], load_plugins()) == 0
    assert (scene / "city_SE3_egovehicle.feather").is_file() and not (scene / "ego_pose").exists()
    env = dict(os.environ, COLUMNS="200", OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "omnire.cli", "train", "3dgs", "argoverse2", "--data", str(scene),
                          "--scale", "1.0", "--trainer.max-steps", "3", "--trainer.no-progress",
                          "--trainer.eval-train-views", "2", "--method.rasterizer", "torch",
                          "--method.nodes.background.max-lidar-points", "2000",
                          "--method.nodes.background.num-far-points", "200",
                          "--trainer.output-dir", str(tmp_path / "runs")],
                         capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "av2_av2_scene" in out.stdout and any((tmp_path / "runs").rglob("run.json"))
