"""nuScenes reader on synthetic multi-frame scenes written in the nuScenes layout: round trip
against the processed reader and the generator's ground truth, frame choice, asynchronous
cameras, streamed tables, errors, and a short `omnire train` run."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tracemalloc
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from omnire.api import ConfigError, interpolate_poses, interpolate_track, nearest_index
from omnire_nuscenes import (
    CAMERAS,
    NuScenesConfig,
    NuScenesDataError,
    NuScenesFileMissing,
    category_of,
    frame_targets,
    iter_json_array,
)
from omnire_nuscenes.writer import FIRST_US, LOGFILE, VERSION, token, write_nuscenes

FRAMES = 11  # keyframes 0, 5, 10 at 10 fps


def parse(data: Path, **kw):
    return NuScenesConfig(data=data, scale=1.0, **kw).setup().parse()


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from omnire_processed.reader import ProcessedDataparser, ProcessedDataparserConfig
    from omnire_synthetic.generate import SynthOptions, generate

    root = tmp_path_factory.mktemp("nuscenes")
    proc = root / "processed"
    generate(proc, "urban", SynthOptions(frames=FRAMES, width=48, height=32, num_cameras=6, lidar_beams=16,
                                         lidar_azimuth_step_deg=0.8, write_depth=False))
    out = root / "nuscenes"
    out.mkdir()
    summary = write_nuscenes(proc, out)
    reader = ProcessedDataparser(ProcessedDataparserConfig(data=proc, scale=1.0, holdout_every=0, load_human_poses=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = reader.parse()
    with np.load(proc / "ground_truth.npz") as z:
        gt = {k: z[k] for k in z.files}
    ego = gt["ego_to_world"]
    # processed-reader world -> this reader's world (origin at the first ego pose)
    M = np.linalg.inv(ego[0]) @ np.linalg.inv(reader.world_from_file @ gt["file_from_generator"])
    return SimpleNamespace(proc=proc, out=out, summary=summary, ref=ref, gt=gt, M=M, scene=parse(out), root=root)


def small_copy(synth, tmp_path: Path) -> Path:
    dst = tmp_path / "nus"
    shutil.copytree(synth.out, dst)
    return dst


def rewrite_table(root: Path, name: str, edit) -> None:
    path = root / VERSION / f"{name}.json"
    records = json.loads(path.read_text())
    records = edit(records) or records
    path.write_text(json.dumps(records, indent=0))


# ---------------------------------------------------------------------------- layout
def test_layout_is_nuscenes_like(synth):
    tables = synth.out / VERSION
    for name in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor", "sample_annotation",
                 "instance", "category", "log", "attribute", "visibility", "map"):
        assert (tables / f"{name}.json").is_file(), name
    assert synth.summary["keyframes"] == [0, 5, 10]
    sds = json.loads((tables / "sample_data.json").read_text())
    lidar = [s for s in sds if "LIDAR_TOP" in s["filename"]]
    assert len(lidar) == FRAMES and sum(s["is_key_frame"] for s in lidar) == 3
    key = next(s for s in lidar if s["is_key_frame"])
    assert key["filename"] == f"samples/LIDAR_TOP/{LOGFILE}__LIDAR_TOP__{FIRST_US}.pcd.bin"
    assert key["fileformat"] == "pcd" and key["ego_pose_token"] == key["token"]
    assert (synth.out / key["filename"]).stat().st_size % 20 == 0  # float32 x y z intensity ring
    cams = [s for s in sds if s["fileformat"] == "jpg"]
    assert len(cams) == 6 * FRAMES and all(s["width"] == 48 and s["height"] == 32 for s in cams)
    assert all(s["filename"].startswith("sweeps/") != s["is_key_frame"] for s in sds)
    anns = json.loads((tables / "sample_annotation.json").read_text())
    assert all(len(a["size"]) == 3 and len(a["rotation"]) == 4 for a in anns)
    assert any(a["num_lidar_pts"] > 0 for a in anns)
    modality = {r["token"]: r["modality"] for r in json.loads((tables / "sensor.json").read_text())}
    cal = json.loads((tables / "calibrated_sensor.json").read_text())
    assert sorted(modality[c["sensor_token"]] for c in cal) == ["camera"] * 6 + ["lidar"]
    assert all((c["camera_intrinsic"] == []) == (modality[c["sensor_token"]] == "lidar") for c in cal)


# ---------------------------------------------------------------------------- round trip
def test_frames_cameras_and_timestamps(synth):
    s, ref = synth.scene, synth.ref
    assert s.num_frames == FRAMES and [c.name for c in s.cameras] == list(CAMERAS)
    assert np.allclose(s.frame_timestamps - s.frame_timestamps[0], ref.frame_timestamps - ref.frame_timestamps[0],
                       atol=1e-6)
    assert np.isclose(s.frame_timestamps[0], FIRST_US * 1e-6)
    for mine, theirs in zip(s.cameras, ref.cameras):
        assert (mine.width, mine.height) == (theirs.width, theirs.height) == (48, 32)
        assert np.allclose(mine.intrinsics, theirs.intrinsics, atol=1e-9)
        assert np.allclose(mine.cam_to_world, synth.M[None] @ theirs.cam_to_world, atol=1e-8)
        assert np.array_equal(mine.timestamps, s.frame_timestamps)  # synchronous synthetic cameras
        assert mine.distortion is None
        for a, b in zip(mine.image_paths, theirs.image_paths):
            assert Path(a).read_bytes() == Path(b).read_bytes()
        assert mine.extras["is_key_frame"].tolist() == [f in (0, 5, 10) for f in range(FRAMES)]


def test_hand_written_calibration_gives_the_same_camera_in_both_readers(synth, tmp_path):
    """A devkit calibrated_sensor table written by hand: camera_intrinsic is used as is (pixel
    centres at +0.5, docs/datasets.md) and scaled; the processed reader, given the same four
    numbers in intrinsics/0.txt as the reference's nuScenes preprocessing writes them, gives
    the same K. Expected values computed by hand."""
    from omnire_processed.reader import ProcessedDataparser, ProcessedDataparserConfig

    root = small_copy(synth, tmp_path)
    cam_front = [[40.0, 0.0, 24.5], [0.0, 44.0, 15.75], [0.0, 0.0, 1.0]]
    forward = [0.5, -0.5, 0.5, -0.5]  # w x y z: camera x = -ego y, y = -ego z, z = ego x
    rows = [{"token": token("calibrated_sensor", LOGFILE, "LIDAR_TOP"), "sensor_token": token("sensor", "LIDAR_TOP"),
             "translation": [0.9, 0.0, 1.8], "rotation": [1.0, 0.0, 0.0, 0.0], "camera_intrinsic": []}]
    for ch in CAMERAS:
        rows.append({"token": token("calibrated_sensor", LOGFILE, ch), "sensor_token": token("sensor", ch),
                     "translation": [1.5, 0.0, 1.6], "rotation": forward,
                     "camera_intrinsic": cam_front if ch == "CAM_FRONT" else [[30.0, 0.0, 24.0], [0.0, 30.0, 16.0],
                                                                               [0.0, 0.0, 1.0]]})
    (root / VERSION / "calibrated_sensor.json").write_text(json.dumps(rows))
    s = NuScenesConfig(data=root, scale=0.5, load_lidar=False).setup().parse()
    front = s.cameras[0]
    assert front.name == "CAM_FRONT" and (front.width, front.height) == (24, 16)  # 48x32 at 0.5
    expected = np.array([[20.0, 0.0, 12.25], [0.0, 22.0, 7.875], [0.0, 0.0, 1.0]])  # (fx, fy, cx, cy) / 2
    assert np.array_equal(front.intrinsics, expected)
    # The camera's pose in the ego frame of frame 0 (synchronous synthetic sensors): the row's.
    c2w = np.linalg.inv(s.ego_poses[0]) @ front.cam_to_world[0]
    assert np.allclose(c2w[:3, 3], [1.5, 0.0, 1.6], atol=1e-12)
    assert np.allclose(c2w[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)

    proc = tmp_path / "processed"
    shutil.copytree(synth.proc, proc)
    (proc / "intrinsics" / "0.txt").write_text("40 44 24.5 15.75 0 0 0 0 0\n")
    reader = ProcessedDataparser(ProcessedDataparserConfig(data=proc, source="nuscenes", cameras=(0,), scale=0.5,
                                                           load_lidar=False, load_human_poses=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        theirs = reader.parse().cameras[0]
    assert theirs.name == "CAM_FRONT" and reader.pixel_centres == "half"
    assert np.array_equal(theirs.intrinsics, expected)


def test_world_and_ego(synth):
    s, ego = synth.scene, synth.gt["ego_to_world"]
    assert np.allclose(s.ego_poses, np.linalg.inv(ego[0])[None] @ ego, atol=1e-9)
    assert np.allclose(s.ego_poses[0], np.eye(4), atol=1e-12)
    front = s.cameras[0].cam_to_world[0]
    assert front[0, 2] > 0.99 and front[2, 1] < -0.99  # looks along +x, image y down = world -z


def test_lidar_round_trip(synth):
    s, ref = synth.scene, synth.ref
    for f in range(FRAMES):
        mine, theirs = s.lidar.points[f], ref.lidar.points[f].astype(np.float64)
        expected = theirs @ synth.M[:3, :3].T + synth.M[:3, 3]
        assert mine.shape == expected.shape and mine.dtype == np.float32
        assert np.abs(mine - expected).max() < 5e-5
    origins = ref.lidar.origins @ synth.M[:3, :3].T + synth.M[:3, 3]
    assert np.allclose(s.lidar.origins, origins, atol=1e-6)


def test_lidar_intensity_ring_and_sensor_pose(synth):
    """Intensity (0-255 / 255: the processed copy's, which its reader maps to [0, 1] too) and
    ring (beam of the HDL-32E model) ride along; the sensor
    pose is LIDAR_TOP's in x-forward axes (x = the ego's heading on the synthetic car)."""
    s, ref = synth.scene, synth.ref
    lidar = s.lidar
    assert lidar.beam_model.name == "Velodyne HDL-32E" and lidar.beam_model.num_beams == 32
    for f in range(FRAMES):
        assert lidar.intensity[f].dtype == np.float32 and 0 <= lidar.intensity[f].min() <= lidar.intensity[f].max() <= 1
        np.testing.assert_allclose(lidar.intensity[f], ref.lidar.intensity[f], atol=1e-6)
        # The writer's ring: the elevation (z up) spread over 16 rings from -25 to 10 degrees.
        rel = lidar.points[f].astype(np.float64) - lidar.origins[f]
        el = np.degrees(np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1])))
        ring = np.clip(np.round((el + 25.0) / 35.0 * 15), 0, 15)
        assert lidar.beams[f].dtype == np.int16 and np.mean(lidar.beams[f] == ring) > 0.99
        assert lidar.sensor_to_world[f][:3, 0] @ s.ego_poses[f][:3, 0] > 0.999
        np.testing.assert_allclose(lidar.sensor_to_world[f][:3, 3], lidar.origins[f])
    assert lidar.times is None


def test_boxes_round_trip_and_interpolation(synth):
    s, ref, gt = synth.scene, synth.ref, synth.gt
    keys = np.array([0, 5, 10])
    t = s.frame_timestamps
    mine = {tr.track_id: tr for tr in s.tracks}
    true_to_mine = np.linalg.inv(gt["ego_to_world"][0])
    checked, worst = 0, 0.0
    for tr in ref.tracks:
        kf = keys[tr.present[keys]]
        tok = token("instance", LOGFILE, tr.track_id)
        if len(kf) == 0:
            assert tok not in mine
            continue
        m = mine[tok]
        assert np.allclose(m.size, tr.size, atol=1e-9)
        poses = synth.M[None] @ tr.poses
        assert np.allclose(m.poses[kf], poses[kf], atol=1e-6)  # annotated keyframes: exact
        exp_poses, exp_present = interpolate_track(t[kf], poses[kf], np.ones(len(kf), bool), t, max_gap=1.0)
        assert np.array_equal(m.present, exp_present)
        assert np.allclose(m.poses[m.present], exp_poses[m.present], atol=1e-6)
        k = list(gt["track_ids"]).index(tr.track_id)
        truth = true_to_mine[None] @ gt["box_poses_true"][k]
        worst = max(worst, np.linalg.norm(m.poses[m.present, :3, 3] - truth[m.present, :3, 3], axis=1).max())
        assert np.einsum("fi,fi->f", m.poses[m.present, :3, 0], truth[m.present, :3, 0]).min() > 0.99  # heading
        assert m.category == category_of(m.class_name) and m.class_name.split(".")[0] in ("vehicle", "human")
        checked += 1
    print(f"{checked} tracks; interpolated boxes within {worst:.3f} m of the true motion")
    assert checked >= 5 and worst < 0.1, (checked, worst)


def test_box_sizes_are_length_width_height(synth):
    ann = json.loads((synth.out / VERSION / "sample_annotation.json").read_text())
    sizes = {a["instance_token"]: a["size"] for a in ann}
    for tr in synth.scene.tracks:
        w, l, h = sizes[tr.track_id]
        assert np.allclose(tr.size, [l, w, h])
        if tr.category == "vehicle":
            assert tr.size[0] > tr.size[1]


def test_annotation_gap(synth, tmp_path):
    root = small_copy(synth, tmp_path)
    full = [t for t in synth.scene.tracks if t.present.all()][0]
    middle = full.extras["annotation_tokens"][1]  # keyframe 5
    rewrite_table(root, "sample_annotation", lambda r: [a for a in r if a["token"] != middle])
    s = {t.track_id: t for t in parse(root, load_lidar=False).tracks}  # gap 1.0 s <= max_track_gap
    assert s[full.track_id].present.all()
    ends = full.extras["annotation_poses"][[0, 2]]
    expected = interpolate_poses(np.array([0.0, 1.0]), ends, np.arange(FRAMES) / 10)
    assert np.allclose(s[full.track_id].poses, expected, atol=1e-9)
    s = {t.track_id: t for t in parse(root, load_lidar=False, max_track_gap=0.6).tracks}
    assert s[full.track_id].present.tolist() == [True] + [False] * 9 + [True]


# ---------------------------------------------------------------------------- frame choice
def test_nearest_and_targets():
    times = np.array([0.0, 10.0, 20.0, 30.0])
    assert nearest_index(times, np.array([-5.0, 4.0, 5.0, 6.0, 29.0, 99.0])).tolist() == [0, 0, 0, 1, 3, 3]
    assert nearest_index(np.array([7.0]), np.array([1.0, 9.0])).tolist() == [0, 0]
    assert frame_targets(np.array([0, 500000, 1000000]), 4).tolist() == [0, 100000, 200000, 300000, 400000, 500000,
                                                                         600000, 700000, 800000, 900000, 1000000]
    assert frame_targets(np.array([0, 500000]), 0).tolist() == [0, 500000]


def test_keyframes_only_and_other_rates(synth):
    s0 = parse(synth.out, interpolate_frames=0, load_lidar=False)
    assert np.allclose((s0.frame_timestamps - s0.frame_timestamps[0]) * 10, [0, 5, 10])
    full = {tr.track_id: tr for tr in synth.scene.tracks}
    for tr in s0.tracks:  # keyframe boxes are the annotations themselves
        assert np.array_equal(tr.present, full[tr.track_id].present[[0, 5, 10]])
        assert np.allclose(tr.poses[tr.present], full[tr.track_id].poses[[0, 5, 10]][tr.present], atol=1e-9)
    s1 = parse(synth.out, interpolate_frames=1, load_lidar=False)  # midpoints 2.5, 7.5: ties take the earlier sweep
    assert np.allclose((s1.frame_timestamps - s1.frame_timestamps[0]) * 10, [0, 2, 5, 7, 10])
    s9 = parse(synth.out, interpolate_frames=9, load_lidar=False)  # 20 Hz targets on 10 Hz sweeps: each sweep once
    assert s9.num_frames == FRAMES
    part = parse(synth.out, start_frame=3, end_frame=7, cameras=("CAM_BACK",), load_lidar=False)
    assert part.source_frames.tolist() == [3, 4, 5, 6] and [c.name for c in part.cameras] == ["CAM_BACK"]
    assert np.allclose(part.ego_poses[0], np.eye(4), atol=1e-12)  # the origin moves to the first loaded frame


def test_asynchronous_cameras(synth, tmp_path):
    delays = [0.0, 0.004, 0.01, 0.03, 0.06, -0.02]
    out = tmp_path / "async"
    out.mkdir()
    write_nuscenes(synth.proc, out, camera_delays=delays)
    s = parse(out, load_lidar=False)
    gt = synth.gt
    times, ego, c2e = gt["timestamps"], gt["ego_to_world"], gt["cam_to_ego"]
    assert np.allclose(s.frame_timestamps - FIRST_US * 1e-6, times, atol=1e-6)
    for c, (cam, d) in enumerate(zip(s.cameras, delays)):
        # nearest image: a camera firing 60 ms late is nearer the frame after it
        idx = np.maximum(np.arange(FRAMES) - 1, 0) if d > 0.05 else np.arange(FRAMES)
        us = np.round(cam.timestamps * 1e6).astype(np.int64) - FIRST_US
        assert us.tolist() == np.round((times[idx] + d) * 1e6).astype(np.int64).tolist()
        expected = np.linalg.inv(ego[0])[None] @ interpolate_poses(times, ego, times[idx] + d) @ c2e[c]
        assert np.allclose(cam.cam_to_world, expected, atol=1e-8)


# ---------------------------------------------------------------------------- tables
def test_streamed_json_matches_json_load(synth):
    path = synth.out / VERSION / "sample_data.json"
    whole = json.loads(path.read_text())
    for chunk in (1, 7, 100, 1 << 20):
        assert list(iter_json_array(path, chunk_chars=chunk)) == whole


def test_streaming_memory_is_bounded(tmp_path):
    path = tmp_path / "ego_pose.json"
    rec = {"token": "0" * 32, "timestamp": 1532402927647951, "rotation": [0.5, 0.5, 0.5, 0.5],
           "translation": [411.3, 1180.9, 0.0]}
    path.write_text(json.dumps([dict(rec, token=f"{i:032x}") for i in range(25000)], indent=0))
    size = path.stat().st_size
    tracemalloc.start()
    kept = sum(1 for r in iter_json_array(path, chunk_chars=1 << 16) if r["token"].endswith("00"))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert kept == 98 and size > 3.5e6 and peak < 1e6, (size, peak)


@pytest.mark.parametrize("text,match", [
    ('{"token": 1}', "expected '\\['"),
    ('[{"token": "a"}, {"token": ', "invalid JSON near character"),
    ('[{"token": "a"} {"token": "b"}]', "expected ',' or '\\]'"),
    ('[{"token": "a"}] x', "data after the closing"),
    ('[{"token": "a"},', "file ends inside the array"),
])
def test_malformed_json(tmp_path, text, match):
    path = tmp_path / "t.json"
    path.write_text(text)
    with pytest.raises(NuScenesDataError, match=match) as err:
        list(iter_json_array(path, chunk_chars=4))
    assert str(path) in str(err.value)


# ---------------------------------------------------------------------------- errors
def test_error_missing_table(synth, tmp_path):
    root = small_copy(synth, tmp_path)
    (root / VERSION / "ego_pose.json").unlink()
    with pytest.raises(NuScenesFileMissing, match=r"ego_pose\.json: missing nuScenes table 'ego_pose'"):
        parse(root)


def test_error_missing_field_and_bad_values(synth, tmp_path):
    root = small_copy(synth, tmp_path)
    rewrite_table(root, "ego_pose", lambda r: [r[0].pop("translation")] and None)
    with pytest.raises(NuScenesDataError, match=r"ego_pose\.json: record 0 \(token '[0-9a-f]{32}'\) lacks field 'translation'"):
        parse(root)
    root = small_copy(synth, tmp_path / "b")
    rewrite_table(root, "calibrated_sensor", lambda r: r[1].update(rotation=[2.0, 0.0, 0.0, 0.0]))
    with pytest.raises(NuScenesDataError, match=r"calibrated_sensor\.json: record '[0-9a-f]+' field 'rotation'.*unit quaternion"):
        parse(root)
    root = small_copy(synth, tmp_path / "c")
    rewrite_table(root, "calibrated_sensor", lambda r: r[1].update(camera_intrinsic=[[1, 0], [0, 1]]))
    with pytest.raises(NuScenesDataError, match=r"field 'camera_intrinsic'.*expected 3x3 finite numbers"):
        parse(root)


def test_error_missing_image_and_bad_lidar(synth, tmp_path):
    root = small_copy(synth, tmp_path)
    img = next((root / "sweeps" / "CAM_FRONT").glob("*.jpg"))
    img.unlink()
    with pytest.raises(NuScenesFileMissing, match=rf"{re.escape(img.name)}: missing image of CAM_FRONT \(sample_data '[0-9a-f]+' field 'filename'\)"):
        parse(root)
    assert parse(root, cameras=("CAM_BACK",), load_lidar=False).num_frames == FRAMES
    pcd = next((root / "sweeps" / "LIDAR_TOP").glob("*.pcd.bin"))
    pcd.write_bytes(pcd.read_bytes()[:-4])
    with pytest.raises(NuScenesDataError, match=r"not a whole number of 20-byte points \(5 float32: x y z intensity ring\)"):
        parse(root, cameras=("CAM_BACK",))
    good = np.fromfile(next(p for p in (root / "samples" / "LIDAR_TOP").glob("*.pcd.bin")), dtype="<f4").reshape(-1, 5)
    for column, value, needle in ((4, 32.0, r"column 5 \(ring\) must hold whole numbers 0..31"),
                                  (4, 1.5, "column 5 \\(ring\\)"), (3, 300.0, r"column 4 \(intensity\) must hold numbers in 0..255")):
        bad = good.copy()
        bad[0, column] = value
        pcd.write_bytes(bad.tobytes())
        with pytest.raises(NuScenesDataError, match=needle):
            parse(root, cameras=("CAM_BACK",))
    pcd.unlink()  # a sweep not downloaded: a gap
    s = parse(root, cameras=("CAM_BACK",))
    assert sum(p is None for p in s.lidar.points) == 1


def test_error_scene_selection(synth, tmp_path):
    root = small_copy(synth, tmp_path)
    with pytest.raises(ConfigError, match=r"scene: 'scene-9999' is neither the name nor the token .*scene-0001"):
        parse(root, scene="scene-9999")
    scene = json.loads((root / VERSION / "scene.json").read_text())[0]
    assert parse(root, scene=scene["token"], load_lidar=False).name == "nuscenes_scene-0001"
    rewrite_table(root, "scene", lambda r: r + [dict(r[0], token="f" * 32, name="scene-0002")])
    with pytest.raises(ConfigError, match=r"holds 2 scenes; choose one by name or token with --scene"):
        parse(root)
    assert parse(root, scene="scene-0001", load_lidar=False).num_frames == FRAMES


def test_error_broken_links(synth, tmp_path):
    root = small_copy(synth, tmp_path)
    rewrite_table(root, "sample", lambda r: r[1].update(next="nope"))
    with pytest.raises(NuScenesDataError, match=r"sample\.json: no sample 'nope' of scene 'scene-0001' \(referenced by sample '[0-9a-f]+' field 'next'\)"):
        parse(root)
    root = small_copy(synth, tmp_path / "b")
    rewrite_table(root, "scene", lambda r: r[0].update(nbr_samples=4))
    with pytest.raises(NuScenesDataError, match=r"field 'nbr_samples' = 4, but its sample chain has 3 samples"):
        parse(root)
    root = small_copy(synth, tmp_path / "c")
    rewrite_table(root, "instance", lambda r: r[0].update(category_token="c" * 32))
    with pytest.raises(NuScenesDataError, match=r"category\.json: no record with token 'c+' \(referenced by instance"):
        parse(root)


def test_error_options(synth, tmp_path):
    with pytest.raises(NuScenesFileMissing, match="nowhere: nuScenes data root does not exist"):
        parse(tmp_path / "nowhere")
    with pytest.raises(NuScenesFileMissing, match=r"v1.0-trainval: no such table folder .* table folders in .*: \['v1.0-mini'\]"):
        parse(synth.out, version="v1.0-trainval")
    with pytest.raises(ConfigError, match=r"cameras: \['CAM_ROOF'\] are not nuScenes cameras"):
        parse(synth.out, cameras=("CAM_ROOF",))
    with pytest.raises(ConfigError, match="select nothing of the 11 frames"):
        parse(synth.out, start_frame=11)
    assert parse(synth.out / VERSION, load_lidar=False).num_frames == FRAMES  # --data at the table folder
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "CAM_BACK.png").write_bytes(b"")
    s = parse(synth.out, load_lidar=False, ego_mask_dir=masks)
    assert [c.ego_mask_path for c in s.cameras] == [None] * 5 + [masks / "CAM_BACK.png"]
    with pytest.raises(NuScenesFileMissing, match="ego_mask_dir does not exist"):
        parse(synth.out, ego_mask_dir=tmp_path / "none")


def test_category_mapping():
    cases = {"vehicle.car": "vehicle", "vehicle.bus.rigid": "vehicle", "vehicle.trailer": "vehicle",
             "vehicle.emergency.police": "vehicle", "vehicle.bicycle": "cyclist", "vehicle.motorcycle": "cyclist",
             "human.pedestrian.adult": "human", "human.pedestrian.police_officer": "human",
             "human.pedestrian.personal_mobility": "cyclist", "human.pedestrian.stroller": "other",
             "animal": "other", "movable_object.trafficcone": "other", "static_object.bicycle_rack": "other"}
    for name, cat in cases.items():
        assert category_of(name) == cat, name


# ---------------------------------------------------------------------------- plugin and CLI
def test_plugin_registered():
    from omnire.plugins import load_plugins

    plugins = load_plugins()
    assert "nuscenes" in plugins.dataparsers.names() and "nuscenes" in plugins.scene_writers.names()
    assert plugins.dataparsers.provenance("nuscenes").distribution == "omnire-dataparser-nuscenes"


def test_synth_format_and_train(tmp_path):
    from omnire.plugins import load_plugins
    from omnire_synthetic.cli import main as synth_main

    scene = tmp_path / "tiny_nuscenes"
    assert synth_main(["urban", str(scene), "--tiny", "--format", "nuscenes"], load_plugins()) == 0
    assert (scene / VERSION / "scene.json").is_file() and not (scene / "images").exists()
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200")
    out = subprocess.run(
        [sys.executable, "-m", "omnire.cli", "train", "3dgs", "nuscenes", "--data", str(scene), "--scale", "1",
         "--trainer.max-steps", "3", "--trainer.no-progress", "--method.rasterizer", "torch",
         "--method.nodes.background.max-lidar-points", "2000", "--method.nodes.background.num-far-points", "200",
         "--trainer.output-dir", str(tmp_path / "runs")],
        capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "nuscenes_scene-0001" in out.stdout
