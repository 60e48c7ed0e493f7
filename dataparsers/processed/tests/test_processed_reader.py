"""Processed-scene reader against scenes from the synthetic generator (each tests the other)."""
from __future__ import annotations

import json
import pickle
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from omnire.data.scene import CATEGORIES, SceneDataError
import omnire_processed.plugin as processed_plugin
from omnire.plugins import load_plugins
from omnire_processed import boxes
from omnire_processed.formats import (
    BOX_HEADING_AXIS,
    CLASS_CATEGORIES,
    PIXEL_CENTRES,
    SOURCES,
    category_of,
    detect_source_from_classes,
)
from omnire_processed.pickles import load_smpl_pickle
from omnire_processed.reader import ProcessedSceneError
from omnire_synthetic.generate import SynthOptions, generate

TINY = dict(frames=8, width=72, height=48, presence_radius=200.0)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("processed_scenes")
    out = {}
    for style, extra in [("pandaset", {}), ("waymo", {"box_noise_translation": 0.2, "drop_pose_frames": 0.3}),
                         ("nuscenes", {"y_down_world": True})]:
        out[style] = root / style
        generate(out[style], "urban", SynthOptions(seed=3, style=style, **TINY, **extra))
    return out


def read(path: Path, **overrides):
    # Through the registry, independent of which other plugins are installed.
    plugins = load_plugins(strict=True, entry_points=False, extra_modules=(processed_plugin,))
    cfg = plugins.dataparsers.get("processed").config_factory()
    cfg.data = path
    cfg.scale = 1.0
    for k, v in overrides.items():
        setattr(cfg, k, v)
    parser = cfg.setup()
    return parser.parse(), parser


def ground_truth(path: Path) -> dict:
    with np.load(path / "ground_truth.npz", allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


def first_pose_file(path: Path) -> np.ndarray:
    pose_dir = path / "ego_pose" if (path / "ego_pose").is_dir() else path / "lidar_pose"
    return np.loadtxt(pose_dir / "000.txt")


def expected_alignment(path: Path, gt: dict) -> np.ndarray:
    """Generator world -> reader world: the reader puts the first written ego pose at the origin."""
    return np.linalg.inv(first_pose_file(path)) @ gt["file_from_generator"]


def project(K: np.ndarray, c2w: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w2c = np.linalg.inv(c2w)
    p = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = p[:, :2] / p[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return uv, p[:, 2]


@pytest.mark.parametrize("style", ["pandaset", "waymo", "nuscenes"])
def test_round_trip_cameras_tracks_poses(scenes, style):
    path = scenes[style]
    scene, parser = read(path)
    gt = ground_truth(path)
    assert parser.source == style
    A = expected_alignment(path, gt)
    F = len(gt["timestamps"])
    assert scene.num_frames == F
    np.testing.assert_allclose(scene.frame_timestamps, gt["timestamps"])
    for c, cam in enumerate(scene.cameras):
        expect = A @ gt["ego_to_world"] @ gt["cam_to_ego"][c]  # (F, 4, 4)
        np.testing.assert_allclose(cam.cam_to_world, expect, atol=1e-6)
        np.testing.assert_allclose(cam.intrinsics, gt["intrinsics"][c], atol=1e-8)
        assert (cam.width, cam.height) == (72, 48)
    # World is z-up after conversion: every camera's up (-y) points to +z.
    ups = -np.concatenate([cam.cam_to_world[:, :3, 1] for cam in scene.cameras])
    assert (ups[:, 2] > 0.95).all()
    tracks = {t.track_id: t for t in scene.tracks}
    assert set(tracks) == set(gt["track_ids"])
    kinds = {"car": "vehicle", "pedestrian": "human", "cyclist": "cyclist"}
    for i, tid in enumerate(gt["track_ids"]):
        tr = tracks[tid]
        assert tr.category == kinds[str(gt["track_kinds"][i])]
        np.testing.assert_array_equal(tr.present, gt["present"][i])
        np.testing.assert_allclose(tr.poses[tr.present], (A @ gt["box_poses_written"][i])[tr.present], atol=1e-6)
        np.testing.assert_allclose(tr.size, gt["box_sizes"][i], atol=1e-9)
        travelled = np.linalg.norm(gt["box_poses_true"][i, -1, :3, 3] - gt["box_poses_true"][i, 0, :3, 3])
        if gt["stationary"][i]:
            assert tr.stationary  # parked cars stay stationary even with noisy boxes
        elif travelled > 1.5:
            assert not tr.stationary
    # Body poses: global orientation back in the (reader's) world, body pose unchanged.
    assert set(scene.human_poses) == set(gt["pedestrian_ids"])
    for j, pid in enumerate(gt["pedestrian_ids"]):
        hp = scene.human_poses[pid]
        valid = gt["pose_valid_written"][j]
        np.testing.assert_array_equal(hp.valid, valid)
        np.testing.assert_allclose(hp.global_orient[valid], A[:3, :3] @ gt["global_orient_written"][j][valid], atol=1e-5)
        np.testing.assert_allclose(hp.body_pose[valid], gt["body_pose_written"][j][valid], atol=1e-6)
        # The body's canonical up axis (SMPL +y) is the world's +z for walkers.
        np.testing.assert_allclose(hp.global_orient[:, :, 1], np.tile([0.0, 0.0, 1.0], (len(valid), 1)), atol=1e-5)
    if style == "waymo":
        assert 0 < gt["pose_valid_written"].mean() < 1  # drops were applied ...
        noise = np.linalg.norm(gt["box_poses_written"][:, :, :2, 3] - gt["box_poses_true"][:, :, :2, 3], axis=-1)
        assert 0.1 < noise.mean() < 0.4  # ... and box noise of std 0.2 m per axis


@pytest.mark.parametrize("style", ["pandaset", "waymo", "nuscenes"])
def test_lidar_lands_on_rendered_depth(scenes, style):
    path = scenes[style]
    scene, _ = read(path)
    assert scene.lidar is not None
    hits, total = 0, 0
    for t in range(scene.num_frames):
        pts = scene.lidar.points[t]
        assert pts is not None and len(pts) > 10000
        for c, cam in enumerate(scene.cameras):
            depth = np.load(path / "depth" / f"{t:03d}_{c}.npy")
            uv, z = project(cam.intrinsics, cam.cam_to_world[t], pts.astype(np.float64))
            ok = (z > 1.0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            u, v = uv[ok].astype(int).T
            rendered = depth[v, u]
            close = np.abs(rendered - z[ok]) < 0.03 * z[ok] + 0.05
            hits += int(close.sum())
            total += int(ok.sum())
    assert total > 1000
    # Pixels are coarse at 72x48, so points near silhouettes may see another surface.
    assert hits / total > 0.85, hits / total
    # The sensor origin of Waymo-style files comes from the origin columns; it sits 1.9 m up.
    if style == "waymo":
        gt = ground_truth(path)
        A = expected_alignment(path, gt)
        expect = (A @ gt["ego_to_world"])[:, :3, 3] + (A @ gt["ego_to_world"])[:, :3, 2] * 1.9
        np.testing.assert_allclose(scene.lidar.origins, expect, atol=1e-4)


def test_nuscenes_y_down_world_converted_to_z_up(scenes):
    path = scenes["nuscenes"]
    # The files really hold a y-down world: the first front camera is the identity.
    np.testing.assert_allclose(np.loadtxt(path / "extrinsics" / "000_0.txt"), np.eye(4), atol=1e-9)
    assert not (path / "ego_pose").exists()
    scene, parser = read(path)
    assert parser.source == "nuscenes"
    # Ground points (LiDAR on the road) are at one height in the converted world (exactly:
    # the ray-traced returns lie on the road plane, so the 20th percentile is that height).
    pts = scene.lidar.points[0]
    low = pts[pts[:, 2] <= np.percentile(pts[:, 2], 20)]
    assert len(low) > 1000 and np.std(low[:, 2]) < 0.2
    # A known point (a box centre, in the file's y-down world) projects to the same pixel
    # through the file's extrinsics/intrinsics and through the converted camera.
    info = json.loads((path / "instances" / "instances_info.json").read_text())
    K_file = np.loadtxt(path / "intrinsics" / "0.txt")
    checked = 0
    for inst in info.values():
        ann = inst["frame_annotations"]
        for t, o2w in zip(ann["frame_idx"], ann["obj_to_world"]):
            X_file = np.asarray(o2w)[:3, 3]
            c2w_file = np.loadtxt(path / "extrinsics" / f"{t:03d}_0.txt")
            p = np.linalg.inv(c2w_file) @ np.append(X_file, 1.0)
            if p[2] < 1.0:
                continue
            # nuScenes intrinsics centre pixels at +0.5 already (formats.PIXEL_CENTRES): no shift.
            uv_file = np.array([K_file[0] * p[0] / p[2] + K_file[2], K_file[1] * p[1] / p[2] + K_file[3]])
            X_ours = parser.world_from_file @ np.append(X_file, 1.0)
            cam = scene.cameras[0]
            uv_ours, z = project(cam.intrinsics, cam.cam_to_world[t], X_ours[None, :3])
            np.testing.assert_allclose(uv_ours[0], uv_file, atol=1e-6)
            assert z[0] == pytest.approx(p[2], rel=1e-9)
            checked += 1
    assert checked > 5


def test_reader_honours_scale_cameras_and_frame_range(scenes):
    scene, _ = read(scenes["pandaset"], scale=0.5, cameras=(2, 0), start_frame=2, end_frame=6)
    gt = ground_truth(scenes["pandaset"])
    assert [c.name for c in scene.cameras] == ["front_right_camera", "front_camera"]
    assert scene.num_frames == 4 and list(scene.source_frames) == [2, 3, 4, 5]
    cam = scene.cameras[0]
    assert (cam.width, cam.height) == (36, 24)
    np.testing.assert_allclose(cam.intrinsics[:2], gt["intrinsics"][2][:2] * 0.5, atol=1e-8)
    # The first loaded frame's ego pose is the origin.
    np.testing.assert_allclose(scene.ego_poses[0], np.eye(4), atol=1e-9)
    assert cam.sky_mask_paths[0].name == "002_2.png"
    assert "fine_dynamic_masks" in str(cam.dynamic_mask_paths["human"][0])


def test_smpl_pickle_written_by_joblib_with_tensors(scenes, tmp_path):
    joblib = pytest.importorskip("joblib")
    torch = pytest.importorskip("torch")
    src = scenes["pandaset"]
    dst = tmp_path / "scene"
    shutil.copytree(src, dst)
    data = pickle.loads((src / "humanpose" / "smpl.pkl").read_bytes())
    # The reference implementation's files hold torch tensors and numpy arrays.
    for v in data.values():
        v["smpl"]["global_orient"] = torch.from_numpy(v["smpl"]["global_orient"])
        v["selected_cam_idx"] = torch.from_numpy(v["selected_cam_idx"])
    joblib.dump(data, dst / "humanpose" / "smpl.pkl")
    a, _ = read(src)
    b, _ = read(dst)
    assert a.human_poses and set(a.human_poses) == set(b.human_poses)
    for k in a.human_poses:
        np.testing.assert_allclose(a.human_poses[k].global_orient, b.human_poses[k].global_orient, atol=1e-7)
        np.testing.assert_array_equal(a.human_poses[k].valid, b.human_poses[k].valid)


def test_smpl_pickle_refuses_code(tmp_path):
    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned",))

    path = tmp_path / "smpl.pkl"
    path.write_bytes(pickle.dumps({0: Evil()}))
    with pytest.raises(pickle.UnpicklingError, match="smpl.pkl.*os.system|smpl.pkl.*posix.system"):
        load_smpl_pickle(path)


def _corrupt_copy(scenes, tmp_path) -> Path:
    dst = tmp_path / "bad"
    shutil.copytree(scenes["pandaset"], dst)
    return dst


def test_bad_input_missing_ego_pose(scenes, tmp_path):
    bad = _corrupt_copy(scenes, tmp_path)
    shutil.rmtree(bad / "ego_pose")
    with pytest.raises(ProcessedSceneError, match=r"ego_pose"):
        read(bad)


def test_bad_input_intrinsics_with_8_numbers(scenes, tmp_path):
    bad = _corrupt_copy(scenes, tmp_path)
    (bad / "intrinsics" / "1.txt").write_text("100 100 36 24 0 0 0 0\n")
    with pytest.raises(ProcessedSceneError, match=r"intrinsics/1\.txt.*9 numbers.*found 8"):
        read(bad)


def test_bad_input_lidar_size_not_multiple_of_row(scenes, tmp_path):
    bad = _corrupt_copy(scenes, tmp_path)
    with open(bad / "lidar" / "003.bin", "ab") as f:
        f.write(b"\0" * 8)
    with pytest.raises(ProcessedSceneError, match=r"lidar/003\.bin.*not a multiple.*20 bytes"):
        read(bad)


def test_intensity_is_read_in_unit_range_from_every_style(scenes):
    """The three styles hold one ray-traced sweep per frame on their datasets' scales
    (PandaSet and nuScenes 0-255, Waymo unbounded): read, each is the generator's intensity
    in [0, 1] (the materials' reflectivity 0.05-0.8 times 0.3-1), equal across styles."""
    read_back = {style: read(path)[0].lidar.intensity for style, path in scenes.items()}
    assert np.fromfile(scenes["pandaset"] / "lidar" / "000.bin", dtype=np.float32).reshape(-1, 5)[:, 3].max() > 100
    compared = 0
    for t, ref in enumerate(read_back["pandaset"]):
        assert ref.dtype == np.float32 and 0.05 * 0.3 - 1e-6 <= ref.min() and ref.max() <= 0.8 + 1e-6
        for style in ("nuscenes", "waymo"):
            if read_back[style][t] is not None:
                np.testing.assert_allclose(read_back[style][t], ref, atol=1e-6, err_msg=f"{style} frame {t}")
                compared += 1
    assert compared >= len(read_back["pandaset"])


@pytest.mark.parametrize("value, expected", [(-1.0, "numbers in 0..255"), (255.5, "numbers in 0..255"),
                                             (np.nan, "numbers in 0..255")])
def test_bad_input_intensity_outside_the_sources_scale(scenes, tmp_path, value, expected):
    bad = _corrupt_copy(scenes, tmp_path)
    path = bad / "lidar" / "003.bin"
    rows = np.fromfile(path, dtype=np.float32).reshape(-1, 5)
    rows[2, 3] = value
    path.write_bytes(rows.tobytes())
    with pytest.raises(ProcessedSceneError, match=r"lidar/003\.bin: column 4 \(intensity, pandaset rows\) must hold "
                                                  + expected + rf" \(found {value:g}, 1 of {len(rows)} values; 0-255"):
        read(bad)


def test_bad_input_instances_beyond_log(scenes, tmp_path):
    bad = _corrupt_copy(scenes, tmp_path)
    path = bad / "instances" / "instances_info.json"
    info = json.loads(path.read_text())
    first = next(iter(info.values()))
    first["frame_annotations"]["frame_idx"][-1] = 50
    path.write_text(json.dumps(info))
    with pytest.raises(ProcessedSceneError, match=r"instances_info\.json.*frame_idx \[50\] outside the log"):
        read(bad)
    assert issubclass(ProcessedSceneError, SceneDataError)


def test_class_maps_cover_all_datasets():
    assert set(CLASS_CATEGORIES) == set(SOURCES)
    for table in CLASS_CATEGORIES.values():
        assert set(table.values()) <= set(CATEGORIES)
    assert category_of("Vehicle", "waymo") == "vehicle"
    assert category_of("human.pedestrian.adult", "nuscenes") == "human"
    assert category_of("BICYCLIST", "argoverse") == "cyclist"
    assert category_of("Person_sitting", "kitti") == "human"
    assert category_of("bicycle", "nuplan") == "cyclist"
    assert category_of("Pedestrian with Object", "pandaset") == "human"
    assert category_of("REGULAR_VEHICLE", "waymo") == "vehicle"  # falls back to other tables
    assert category_of("no such class", "waymo") is None
    assert detect_source_from_classes({"Vehicle", "Pedestrian", "Cyclist"}) == "waymo"
    assert detect_source_from_classes({"REGULAR_VEHICLE", "PEDESTRIAN"}) == "argoverse"
    assert detect_source_from_classes({"Pedestrian"}) is None  # ambiguous


def test_ego_frame_not_z_up_is_turned_up(scenes, tmp_path):
    """A camera-like ego frame (x right, y down, z forward, as in some KITTI exports) still
    yields a z-up world with up_axis=auto, with the same geometry."""
    src = scenes["waymo"]
    dst = tmp_path / "camera_like_ego"
    shutil.copytree(src, dst)
    Q = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # new ego -> old ego
    Qi = np.linalg.inv(Q)
    for p in (dst / "ego_pose").glob("*.txt"):
        np.savetxt(p, np.loadtxt(p) @ Q)
    for p in (dst / "extrinsics").glob("*.txt"):
        np.savetxt(p, Qi @ np.loadtxt(p))
    for p in (dst / "lidar").glob("*.bin"):
        rows = np.fromfile(p, dtype=np.float32).reshape(-1, 14).astype(np.float64)
        for col in (0, 3, 6):  # origin, point, flow
            rows[:, col:col + 3] = rows[:, col:col + 3] @ Qi[:3, :3].T
        rows.astype(np.float32).tofile(p)
    a, _ = read(src)
    b, parser = read(dst, source="waymo")
    assert any("not z-up" in n for n in parser.notes)
    ups = -np.concatenate([cam.cam_to_world[:, :3, 1] for cam in b.cameras])
    assert (ups[:, 2] > 0.95).all()
    # Same scene up to a rigid motion: relative camera motion and LiDAR ranges agree.
    for ca, cb in zip(a.cameras, b.cameras):
        rel_a = np.linalg.inv(ca.cam_to_world[0]) @ ca.cam_to_world
        rel_b = np.linalg.inv(cb.cam_to_world[0]) @ cb.cam_to_world
        np.testing.assert_allclose(rel_a, rel_b, atol=1e-4)
    pa, pb = a.lidar.points[3], b.lidar.points[3]
    np.testing.assert_allclose(np.linalg.norm(pa - a.lidar.origins[3], axis=1),
                               np.linalg.norm(pb - b.lidar.origins[3], axis=1), atol=1e-3)
    np.testing.assert_allclose(pa[:, 2] - a.lidar.origins[3, 2], pb[:, 2] - b.lidar.origins[3, 2], atol=2e-2)


# ---------------------------------------------------------------------------- box axes, pixel centres
def _rewrite_boxes(path: Path, fn) -> None:
    """Apply fn(obj_to_world (n, 4, 4), box_size (n, 3)) -> (obj_to_world, box_size) to every instance."""
    info_path = path / "instances" / "instances_info.json"
    info = json.loads(info_path.read_text())
    for inst in info.values():
        ann = inst["frame_annotations"]
        if not ann["frame_idx"]:
            continue
        o2w, size = fn(np.asarray(ann["obj_to_world"]), np.asarray(ann["box_size"]))
        ann["obj_to_world"], ann["box_size"] = o2w.tolist(), size.tolist()
    info_path.write_text(json.dumps(info))


def _to_x_along(o2w, size):
    """PandaSet-style file boxes (+y = heading, (w, l, h)) -> x along the heading, (l, w, h)."""
    return o2w @ _fix4(1), size[:, [1, 0, 2]]


def _frozen(o2w, size):
    return np.repeat(o2w[:1], len(o2w), 0), size


def _fix4(k):
    m = np.eye(4)
    m[:3, :3] = boxes.axis_fix(k)
    return m


def _read_warned(path: Path, **overrides):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene, parser = read(path, **overrides)
    return scene, parser, [str(w.message) for w in caught if "box" in str(w.message)]


def test_pandaset_style_boxes_are_turned_to_x_along_heading(scenes):
    """The generator writes PandaSet-style boxes as the reference does (local +y = heading);
    motion finds that and the reader turns them (the round trip test checks the poses)."""
    info = json.loads((scenes["pandaset"] / "instances" / "instances_info.json").read_text())
    car = next(v for v in info.values() if v["class_name"] == "Car" and v["frame_annotations"]["frame_idx"])
    w, l, _ = car["frame_annotations"]["box_size"][0]
    assert l > 1.5 * w  # the file lists (width, length, height)
    scene, parser, box_warnings = _read_warned(scenes["pandaset"])
    assert parser.heading_axis.axis == "+y" and parser.heading_axis.reason.startswith("motion")
    assert box_warnings == []
    for style in ("waymo", "nuscenes"):
        _, parser, box_warnings = _read_warned(scenes[style])
        assert parser.heading_axis.axis == "+x" and box_warnings == []


def test_box_axes_from_motion_override_the_source_convention(scenes, tmp_path):
    dst = tmp_path / "x_along"
    shutil.copytree(scenes["pandaset"], dst)
    _rewrite_boxes(dst, _to_x_along)  # a PandaSet scene written by another tool
    a, _ = read(scenes["pandaset"])
    b, parser, box_warnings = _read_warned(dst)
    assert parser.source == "pandaset" and parser.heading_axis.axis == "+x"
    assert len(box_warnings) == 1 and "move along local +x" in box_warnings[0] and "pandaset" in box_warnings[0]
    for ta, tb in zip(a.tracks, b.tracks):
        np.testing.assert_allclose(tb.poses[tb.present], ta.poses[ta.present], atol=1e-9)
        np.testing.assert_allclose(tb.size, ta.size)


def test_box_axes_without_motion(scenes, tmp_path):
    # Frozen boxes: vehicle shapes agree with PandaSet's convention -> no warning.
    frozen = tmp_path / "frozen"
    shutil.copytree(scenes["pandaset"], frozen)
    _rewrite_boxes(frozen, _frozen)
    a, _ = read(scenes["pandaset"])
    b, parser, box_warnings = _read_warned(frozen)
    assert parser.heading_axis.motion.sum() == 0 and parser.heading_axis.shape[1] >= 3
    assert parser.heading_axis.axis == "+y" and box_warnings == []
    ta = next(t for t in a.tracks if t.category == "vehicle")
    tb = next(t for t in b.tracks if t.track_id == ta.track_id)
    f = np.flatnonzero(ta.present)[0]
    np.testing.assert_allclose(tb.poses[f], ta.poses[f], atol=1e-9)
    # Frozen and x-along: shapes contradict the PandaSet convention, the sign is unknown -> warned.
    odd = tmp_path / "frozen_x"
    shutil.copytree(frozen, odd)
    _rewrite_boxes(odd, _to_x_along)
    _, parser, box_warnings = _read_warned(odd)
    assert parser.heading_axis.axis == "+x"
    assert len(box_warnings) == 1 and "ambiguous" in box_warnings[0]
    # Frozen cubes: no evidence at all -> the source's convention, warned.
    cubes = tmp_path / "cubes"
    shutil.copytree(frozen, cubes)
    _rewrite_boxes(cubes, lambda o2w, size: (o2w, np.ones_like(size)))
    _, parser, box_warnings = _read_warned(cubes)
    assert parser.heading_axis.axis == "+y"
    assert len(box_warnings) == 1 and "cannot confirm" in box_warnings[0]
    # An explicit axis is used as given, without checks.
    c, parser, box_warnings = _read_warned(scenes["pandaset"], box_heading_axis="+x")
    assert parser.heading_axis.reason == "configured" and box_warnings == []
    for ta, tc in zip(a.tracks, c.tracks):
        np.testing.assert_allclose(tc.poses[tc.present] @ _fix4(1), ta.poses[ta.present], atol=1e-9)


def test_motion_votes_and_decision_rules():
    t = np.arange(30)
    o2w = np.tile(np.eye(4), (30, 1, 1))
    o2w[:, :3, :3] = boxes.axis_fix(1).T  # file x points to world -y: the heading (world +x) is local +y
    o2w[:, 0, 3] = 0.5 * t  # 5 m/s at 10 Hz
    votes = boxes.motion_votes(t, o2w)
    assert votes[1] >= 25 and votes.sum() == votes[1]
    slow = o2w.copy()
    slow[:, 0, 3] = 0.01 * t  # 0.3 m in total: no displacement reaches MIN_STEP
    assert boxes.motion_votes(t, slow).sum() == 0
    size = np.tile([1.9, 4.5, 1.5], (30, 1))
    moving = [(t, o2w, size, "vehicle")] * 3
    found = boxes.detect_heading_axis(moving, "+x", "waymo")
    assert found.axis == "+y" and "following the motion" in found.warning
    assert boxes.detect_heading_axis(moving, "+y", "pandaset").warning is None
    # One moving track decides only with agreeing shapes.
    parked = [(t, np.repeat(o2w[:1], 30, 0), size, "vehicle")] * 3
    assert boxes.detect_heading_axis(moving[:1] + parked, "+x", "waymo").axis == "+y"
    lone = boxes.detect_heading_axis([(t, o2w, np.tile([2.0, 2.0, 1.5], (30, 1)), "human")], "+x", "waymo")
    assert lone.axis == "+x" and "cannot confirm" in lone.warning
    np.testing.assert_allclose(boxes.size_fix(size, 1)[0], [4.5, 1.9, 1.5])


def test_pixel_centre_convention_per_source(scenes, tmp_path):
    assert set(PIXEL_CENTRES) == set(SOURCES) == set(BOX_HEADING_AXIS)
    assert {s for s, c in PIXEL_CENTRES.items() if c == "integer"} == {"argoverse", "kitti", "nuplan"}
    gt = ground_truth(scenes["pandaset"])
    scene, parser = read(scenes["pandaset"])
    assert parser.pixel_centres == "half"
    np.testing.assert_allclose(scene.cameras[0].intrinsics, gt["intrinsics"][0], atol=1e-8)
    # The same calibration written in OpenCV's convention (as Argoverse2, KITTI, NuPlan are):
    # cx, cy 0.5 px smaller in the file, +0.5 when read; scaled as continuous coordinates.
    dst = tmp_path / "opencv_k"
    shutil.copytree(scenes["pandaset"], dst)
    for f in (dst / "intrinsics").glob("*.txt"):
        v = np.loadtxt(f)
        v[2:4] -= 0.5
        np.savetxt(f, v)
    scene, parser = read(dst, file_pixel_centres="integer", scale=0.5)
    assert parser.pixel_centres == "integer"
    np.testing.assert_allclose(scene.cameras[0].intrinsics[:2], gt["intrinsics"][0][:2] * 0.5, atol=1e-8)


def test_lens_distortion_is_undistorted_at_load(scenes, tmp_path):
    """k1 k2 p1 p2 k3 in intrinsics/<cam>.txt (the reference keeps Waymo's distorted images)
    reach CameraSequence.distortion, and the training image is the undistorted file."""
    from omnire.data.images import ImageCache, read_image, undistort
    import torch

    copy = _corrupt_copy(scenes, tmp_path)
    plain, _ = read(copy)
    assert all(c.distortion is None for c in plain.cameras)  # all-zero coefficients: pinhole
    vals = np.loadtxt(copy / "intrinsics" / "0.txt").reshape(-1)
    vals[4:] = [-0.3, 0.08, 0.001, -0.002, 0.0]
    np.savetxt(copy / "intrinsics" / "0.txt", vals[None])
    scene, _ = read(copy)
    cam = scene.cameras[0]
    np.testing.assert_allclose(cam.distortion, vals[4:])
    np.testing.assert_allclose(cam.intrinsics, plain.cameras[0].intrinsics)
    assert scene.cameras[1].distortion is None
    loaded = ImageCache().camera_image(cam, 0)
    raw = torch.from_numpy(read_image(cam.image_paths[0], cam.width, cam.height, 3))
    expected = undistort(raw, cam.intrinsics, cam.distortion).float() / 255.0
    assert torch.equal(loaded, expected)
    assert float((loaded - raw.float() / 255.0).abs().mean()) > 0.01  # a real warp, not a copy
    vals[4] = np.nan
    np.savetxt(copy / "intrinsics" / "0.txt", vals[None])
    with pytest.raises(ProcessedSceneError, match=r"intrinsics/0\.txt.*distortion"):
        read(copy)
