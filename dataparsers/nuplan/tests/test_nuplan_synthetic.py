"""nuPlan reader on a synthetic log written by the ``nuplan`` scene writer: the generator's
ground truth (poses, boxes, intrinsics, points) back through the reader, frame choice, and a
real ``omnire train`` run that trains and evaluates."""
from __future__ import annotations

import json
import os
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from omnire.api import first_pose_world, interpolate_poses, rigid
from omnire_nuplan import CAMERAS, NuPlanConfig, category_of, parse_pcd
from omnire_nuplan.database import NuPlanDataError
from omnire_nuplan.pointcloud import write_pcd
from omnire_nuplan.writer import (
    FIRST_US,
    LIDAR_TO_EGO_ROTATION,
    LOG,
    blobs_path,
    database_path,
    load_source,
    synthetic_beam_model,
    write_nuplan,
)

FRAMES = 6


def parse(data: Path, **kw):
    return NuPlanConfig(data=data, scale=1.0, holdout_every=0, **kw).setup().parse()


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from omnire_synthetic.generate import SynthOptions, generate

    root = tmp_path_factory.mktemp("nuplan")
    proc = root / "processed"
    generate(proc, "urban", SynthOptions(frames=FRAMES, width=48, height=32, num_cameras=6, lidar_beams=16,
                                         lidar_azimuth_step_deg=1.0, write_depth=False))
    out = root / "nuplan"
    src = load_source(proc)
    summary = write_nuplan(src, out)
    with np.load(out / "ground_truth.npz") as z:
        gt = {k: z[k] for k in z.files}
    G = gt["file_from_generator"]  # generator world -> nuPlan global
    E = first_pose_world(G @ gt["ego_to_world"][0]) @ G  # generator world -> the reader's world
    return SimpleNamespace(out=out, src=src, summary=summary, gt=gt, E=E, scene=parse(out))


def test_layout_is_nuplan(synth):
    db = database_path(synth.out)
    assert db.parent.parts[-3:] == ("nuplan-v1.1", "splits", "mini") and db.stem == LOG
    conn = sqlite3.connect(db)
    try:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        assert {"log", "scene", "ego_pose", "camera", "image", "lidar", "lidar_pc", "lidar_box", "track",
                "category"} <= tables
        assert conn.execute("SELECT COUNT(*) FROM lidar_pc").fetchone()[0] == 2 * FRAMES - 1  # 20 Hz
        assert conn.execute("SELECT COUNT(*) FROM image").fetchone()[0] == 6 * FRAMES  # 10 Hz
        tok, fn = conn.execute("SELECT token, filename FROM lidar_pc ORDER BY timestamp").fetchone()
        assert isinstance(tok, bytes) and len(tok) == 8
        assert fn == f"{LOG}/MergedPointCloud/{tok.hex()}.pcd"
        channels = [r[0] for r in conn.execute("SELECT channel FROM camera")]
        assert sorted(channels) == sorted(CAMERAS[:6])
    finally:
        conn.close()
    rec = parse_pcd((blobs_path(synth.out) / fn).read_bytes(), Path(fn))
    assert rec.dtype.names == ("x", "y", "z", "intensity", "ring", "lidar_info")
    assert rec["intensity"].max() > 1.0  # 0-255, as merged clouds hold it


def test_frames_and_timestamps(synth):
    s = synth.scene
    assert s.num_frames == FRAMES and s.name == f"nuplan_{LOG}"
    assert [c.name for c in s.cameras] == list(CAMERAS[:6])
    expected = (FIRST_US + np.round(synth.gt["timestamps"] * 1e6)) * 1e-6
    assert np.allclose(s.frame_timestamps, expected, atol=1e-6)
    assert s.source_frames.tolist() == [2 * f for f in range(FRAMES)]  # every second lidar_pc
    for cam in s.cameras:
        assert np.array_equal(cam.timestamps, s.frame_timestamps) and cam.distortion is None


def test_ground_truth_poses_intrinsics(synth):
    s, gt, E = synth.scene, synth.gt, synth.E
    ego = gt["ego_to_world"]
    assert np.abs(s.ego_poses - E[None] @ ego).max() < 1e-6
    for c, cam in enumerate(s.cameras):
        assert np.abs(cam.intrinsics - gt["intrinsics"][c]).max() < 1e-6
        assert np.abs(cam.cam_to_world - E[None] @ ego @ gt["cam_to_ego"][c]).max() < 1e-6
        for f, path in enumerate(cam.image_paths):
            assert Path(path).read_bytes() == Path(synth.src.scene.cameras[c].image_paths[f]).read_bytes()


def test_ground_truth_boxes(synth):
    s, gt, E = synth.scene, synth.gt, synth.E
    assert len(s.tracks) == int(gt["present"].any(axis=1).sum()) > 0
    # Track tokens are the writer's per-actor tokens; match tracks through their category and poses.
    for i in range(len(gt["track_ids"])):
        present = gt["present"][i].astype(bool)
        if not present.any():
            continue
        want = E[None] @ gt["box_poses_written"][i]
        hits = [t for t in s.tracks if np.array_equal(t.present, present)
                and np.abs(t.poses[present] - want[present]).max() < 1e-6]
        assert len(hits) == 1, f"actor {gt['track_ids'][i]}"
        t = hits[0]
        assert np.abs(t.size - gt["box_sizes"][i]).max() < 1e-6  # (length, width, height)
        kind = str(gt["track_kinds"][i])
        assert t.category == {"car": "vehicle", "pedestrian": "human", "cyclist": "cyclist"}[kind]


def test_lidar_points(synth):
    """Points and intensity (the blobs' 0-255 / 255) are the generator's."""
    s, E = synth.scene, synth.E
    for f in range(FRAMES):
        want = synth.src.points(f) @ E[:3, :3].T + E[:3, 3]
        got = s.lidar.points[f]
        assert got.shape == want.shape and np.abs(got - want).max() < 1e-4  # float32 blobs
        value = s.lidar.intensity[f]
        assert value.dtype == np.float32 and 0 <= value.min() <= value.max() <= 1
        np.testing.assert_allclose(value, synth.src.intensity[f], atol=1e-6)
    origin = synth.E @ synth.gt["ego_to_world"][0] @ np.append(synth.src.lidar_to_ego[:3, 3], 1.0)
    assert np.abs(s.lidar.origins[0] - origin[:3]).max() < 1e-6


def _blob(root: Path, frame: int) -> Path:
    """The MergedPointCloud blob of ``frame`` (lidar_pc 2 * frame)."""
    conn = sqlite3.connect(database_path(root))
    try:
        fn = conn.execute("SELECT filename FROM lidar_pc ORDER BY timestamp").fetchall()[2 * frame][0]
    finally:
        conn.close()
    return blobs_path(root) / fn


def test_lidar_beams_and_beam_model(synth):
    """The top LiDAR's rings (lidar_info 0) are the beams, the back LiDAR's returns -1; the
    elevations measured from the returns are the synthetic LiDAR's; the sensor pose is the
    lidar row's; the format records no point times."""
    lidar, E = synth.scene.lidar, synth.E
    want = synthetic_beam_model(synth.src)
    model = lidar.beam_model
    assert model.num_beams == want.num_beams == 16
    assert np.abs(model.elevations_deg - want.elevations_deg).max() < 0.05
    assert model.azimuth_resolution_deg == pytest.approx(want.azimuth_resolution_deg, abs=1e-3)
    assert lidar.times is None
    others = 0
    for f in range(FRAMES):
        rec = parse_pcd(_blob(synth.out, f).read_bytes(), Path("blob"))
        top = rec["lidar_info"] == 0
        np.testing.assert_array_equal(lidar.beams[f], np.where(top, rec["ring"], -1))
        others += int((~top).sum())
        sensor = E @ synth.gt["ego_to_world"][f] @ rigid(LIDAR_TO_EGO_ROTATION, synth.src.lidar_to_ego[:3, 3])
        assert np.abs(lidar.sensor_to_world[f] - sensor).max() < 1e-6
    assert others > 0  # the back LiDAR's returns are there, with beam -1


def test_untrusted_rings_leave_no_beams(synth, tmp_path):
    """Rings that are not the top LiDAR's cones (every ring number shuffled at random): no
    beams, one warning saying why, the points still read."""
    root = tmp_path / "log"
    shutil.copytree(synth.out, root)
    rng = np.random.default_rng(0)
    for f in range(FRAMES):
        path = _blob(root, f)
        rec = parse_pcd(path.read_bytes(), path).copy()
        rec["ring"] = rng.integers(0, 16, len(rec))
        path.write_bytes(write_pcd(rec))
    with pytest.warns(UserWarning, match=r"carry no beams .*ring \d+'s returns lie [\d.]+ degrees"):
        s = parse(root)
    assert s.lidar.beams is None and s.lidar.beam_model is None
    assert all(np.array_equal(a, b) for a, b in zip(s.lidar.points, synth.scene.lidar.points))


def test_ring_seen_only_outside_the_measured_sweeps_leaves_no_beams(synth, tmp_path):
    """A top-LiDAR ring that returns only in a sweep the beam model is not measured on (a ring
    aimed at open sky until then): the log still loads, without beams, and one warning names
    the ring (negative and fractional rings are errors: test_nuplan_hostile.py)."""
    root = tmp_path / "log"
    shutil.copytree(synth.out, root)
    path = _blob(root, 4)  # sweeps 0, 2, 3 and 5 of the 6 are measured (ESTIMATE_SWEEPS spread)
    rec = parse_pcd(path.read_bytes(), path).copy()
    rec["ring"][np.flatnonzero(rec["lidar_info"] == 0)[3]] = 16.0
    path.write_bytes(write_pcd(rec))
    with pytest.warns(UserWarning, match=r"carry no beams .*1 of the top LiDAR's 17 rings \(ring 16: 0 returns\)"):
        s = parse(root)
    assert s.lidar.beams is None and s.lidar.beam_model is None
    assert all(np.array_equal(a, b) for a, b in zip(s.lidar.points, synth.scene.lidar.points))


def test_frame_step_range_and_cameras(synth):
    every = parse(synth.out, frame_step=1, load_lidar=False)
    assert every.num_frames == 2 * FRAMES - 1 and every.source_frames.tolist() == list(range(2 * FRAMES - 1))
    # In-between sweeps take the nearest (earlier, on a tie) image.
    assert np.allclose(every.cameras[0].timestamps[1], every.frame_timestamps[0])
    part = parse(synth.out, start_frame=2, end_frame=5, cameras=("CAM_L1", "CAM_F0"), load_lidar=False)
    assert part.num_frames == 3 and [c.name for c in part.cameras] == ["CAM_L1", "CAM_F0"]
    assert np.allclose(part.frame_timestamps, synth.scene.frame_timestamps[2:5])
    scaled = NuPlanConfig(data=database_path(synth.out), scale=0.5, load_lidar=False).setup().parse()
    assert (scaled.cameras[0].width, scaled.cameras[0].height) == (24, 16)
    assert np.allclose(scaled.cameras[0].intrinsics[:2], synth.gt["intrinsics"][0][:2] * 0.5)
    assert len(scaled.test_frames) == 0 or scaled.test_frames.min() > 0


def test_category_mapping():
    assert [category_of(n) for n in ("vehicle", "pedestrian", "bicycle", "traffic_cone", "barrier", "czone_sign",
                                     "generic_object")] == ["vehicle", "human", "cyclist"] + ["other"] * 4


def test_max_track_gap_bridges_a_missing_box(synth, tmp_path):
    """A track's box deleted on one frame's lidar_pc: absent there by default (nuPlan boxes
    every lidar_pc), interpolated from its neighbours with --max-track-gap."""
    track = next(t for t in synth.scene.tracks if t.present[:3].all())
    k = int(np.flatnonzero(track.present)[:2][1])  # its box on frame 1 (present on 0..2)
    assert k == 1
    root = tmp_path / "log"
    shutil.copytree(synth.out, root)
    conn = sqlite3.connect(database_path(root))
    conn.execute("DELETE FROM lidar_box WHERE token = ?", (bytes.fromhex(track.extras["box_tokens"][k]),))
    conn.commit()
    conn.close()
    gap = {t.track_id: t for t in parse(root, load_lidar=False).tracks}[track.track_id]
    assert gap.present.tolist() == [f != 1 and p for f, p in enumerate(track.present)]
    assert np.array_equal(gap.poses[gap.present], track.poses[gap.present])
    bridged = {t.track_id: t for t in parse(root, load_lidar=False, max_track_gap=0.25).tracks}[track.track_id]
    assert np.array_equal(bridged.present, track.present)
    t = synth.scene.frame_timestamps
    expected = interpolate_poses(t[[0, 2]], track.poses[[0, 2]], t[1:2])[0]
    assert np.abs(bridged.poses[1] - expected).max() < 1e-9


def test_lidar_intensity_outside_0_255_is_refused(synth, tmp_path):
    root = tmp_path / "log"
    shutil.copytree(synth.out, root)
    conn = sqlite3.connect(database_path(root))
    fn = conn.execute("SELECT filename FROM lidar_pc ORDER BY timestamp").fetchone()[0]
    conn.close()
    path = blobs_path(root) / fn
    rec = parse_pcd(path.read_bytes(), path).copy()
    rec["intensity"][3] = 256.0
    path.write_bytes(write_pcd(rec))
    with pytest.raises(NuPlanDataError, match=rf"{re.escape(fn)}: field intensity must hold numbers in 0..255 "
                                              r"\(found 256, 1 of \d+ values; 0-255 scale\)"):
        parse(root)


def test_explicit_sensor_blobs(synth):
    s = NuPlanConfig(data=database_path(synth.out), sensor_blobs=blobs_path(synth.out), scale=1.0,
                     load_lidar=False).setup().parse()
    assert np.array_equal(s.cameras[0].cam_to_world, synth.scene.cameras[0].cam_to_world)


def test_plugin_listed():
    """``omnire plugins`` (the real CLI) lists the dataparser and the scene writer with their distribution."""
    out = subprocess.run([sys.executable, "-m", "omnire.cli", "plugins"], capture_output=True, text=True,
                         env=dict(os.environ, COLUMNS="250"), timeout=300)
    assert out.returncode == 0, out.stderr
    rows = [line for line in out.stdout.splitlines() if " nuplan " in line]
    assert len(rows) == 2 and all("omnire-dataparser-nuplan" in r for r in rows), out.stdout


def test_synth_format_and_train_omnire(tmp_path):
    """The real CLI: ``omnire synth --format nuplan``, then ``omnire train omnire nuplan``
    trains a few steps and evaluates the held-out frames."""
    from omnire.plugins import load_plugins
    from omnire_synthetic.cli import main as synth_main

    scene = tmp_path / "tiny_nuplan"
    assert synth_main(["urban", str(scene), "--tiny", "--format", "nuplan"], load_plugins()) == 0
    assert database_path(scene).is_file() and not (scene / "images").exists()
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200")
    runs = tmp_path / "runs"
    out = subprocess.run(
        [sys.executable, "-m", "omnire.cli", "train", "omnire", "nuplan", "--data", str(scene), "--scale", "0.5",
         "--cameras", "CAM_F0", "--end-frame", "5", "--holdout-every", "4", "--trainer.max-steps", "3",
         "--trainer.no-progress", "--method.rasterizer", "torch", "--method.nodes.background.max-lidar-points", "1000",
         "--method.nodes.background.num-far-points", "100", "--trainer.output-dir", str(runs)],
        capture_output=True, text=True, env=env, timeout=900)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert f"nuplan_{LOG}" in out.stdout
    metrics = list(runs.rglob("metrics.jsonl"))
    assert len(metrics) == 1, f"metrics under {runs}: {metrics}"
    final = json.loads(metrics[0].read_text().splitlines()[-1])
    assert final["final"] and final["step"] == 3
    psnrs = [v for k, v in _leaves(final["eval"]) if "psnr" in k and isinstance(v, (int, float))]
    assert psnrs and all(np.isfinite(psnrs)), final["eval"]


def _leaves(tree, prefix=""):
    """(dotted key, value) of every leaf of nested dicts."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    else:
        yield prefix, tree
