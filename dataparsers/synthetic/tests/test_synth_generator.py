"""Synthetic scene generator: mesh renderer, LiDAR ray casting, presets, ground truth, CLI."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from omnire_body import lbs, load_template
import omnire_synthetic.plugin as synthetic_plugin
from omnire.plugins import load_plugins
from omnire_synthetic.generate import SynthOptions, generate
from omnire_synthetic.images import read_image
from omnire_synthetic.meshes import quad
from omnire.data.scene import BeamModel
from omnire_synthetic.lidar import GRAZING, NOTHING_HIT, OUT_OF_RANGE, LidarSpec, cast_sweep
from omnire_synthetic.render import rasterize
from omnire_synthetic.world import PRESETS, build_actors, ego_trajectory

TINY = dict(frames=8, width=72, height=48)


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != "ground_truth.json":  # the json records timings
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_rasterizer_exact_depth_and_near_clipping():
    K = np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]])
    # A wall at z = 5 covering the view, and a floor plane y = 1 that crosses the near plane.
    wall = quad([(-20, -20, 5), (20, -20, 5), (20, 20, 5), (-20, 20, 5)], 0, (1, 1))
    floor = quad([(-20, 1, -10), (20, 1, -10), (20, 1, 4.3), (-20, 1, 4.3)], 1, (1, 1))
    verts = torch.from_numpy(np.concatenate([wall.verts, floor.verts]).astype(np.float32))
    faces = torch.from_numpy(np.concatenate([wall.faces, floor.faces + len(wall.verts)]))
    r = rasterize(verts, faces, K, 48, 64, near=0.1)
    assert (r.face >= 0).all()
    rows = torch.arange(48, dtype=torch.float32) + 0.5
    # Above the horizon the wall (depth 5); below, the floor where y/z = (v - cy)/fy hits y = 1.
    floor_z = 1.0 / ((rows - 24.0) / 50.0)
    expect = torch.where((rows > 24.0) & (floor_z < 4.3), floor_z, torch.full_like(rows, 5.0))
    torch.testing.assert_close(r.depth[:, 10], expect, atol=1e-4, rtol=1e-5)
    assert (r.face[-1] >= wall.faces.shape[0]).all()  # the floor owns the bottom row
    torch.testing.assert_close(r.bary.sum(-1), torch.ones(48, 64))


SENSOR_HEIGHT = 1.9


def _sensor(height: float = SENSOR_HEIGHT) -> np.ndarray:
    pose = np.eye(4)
    pose[2, 3] = height
    return pose


def _ground(half: float = 500.0):
    return quad([(-half, -half, 0.0), (half, -half, 0.0), (half, half, 0.0), (-half, half, 0.0)], 0, (1, 1))


def test_lidar_cast_ground_plane_exact_ranges_and_drops():
    """Ground plane 1.9 m below the sensor: range = 1.9 / sin(-elevation) exactly; rays
    above the horizon hit nothing; beyond max range or grazing rays drop."""
    model = BeamModel(np.array([-25.0, -10.0, -3.0, -0.5, 5.0]), 1.0, 100.0, 0.3)
    g = _ground()
    sweep = cast_sweep(g.verts, g.faces, np.zeros(len(g.faces), np.int64), _sensor(), LidarSpec(model, np.array([0.8]), 82.0))
    el = model.elevations_deg[sweep.beam]
    expect = SENSOR_HEIGHT / np.sin(np.deg2rad(-el))  # metres along the ray (inf above the horizon)
    incidence = 90.0 + el  # from the plane's normal
    returned = (el < 0) & (expect <= 100.0) & (incidence <= 82.0)
    np.testing.assert_array_equal(sweep.returned, returned)
    np.testing.assert_allclose(sweep.range[returned], expect[returned], rtol=1e-12)
    assert (sweep.reason[el > 0] == NOTHING_HIT).all()
    assert (sweep.reason[el == -0.5] == OUT_OF_RANGE).all()  # 218 m away
    assert (sweep.reason[el == -3.0] == GRAZING).all()  # 87 degrees from the normal
    cos = np.cos(np.deg2rad(incidence[returned]))
    np.testing.assert_allclose(sweep.intensity[returned], 0.8 * (0.3 + 0.7 * cos), rtol=1e-6)
    assert np.isnan(sweep.intensity[~returned]).all()
    pts = sweep.points_sensor()
    np.testing.assert_allclose(pts[:, 2], -SENSOR_HEIGHT, atol=1e-12)


def test_lidar_cast_box_at_known_distance():
    """A 4 m cube whose near face is 10 m ahead, on the ground: the level beam meets the face
    at x = 10 exactly (range 10 / cos(azimuth)), its material's reflectivity; the sensor pose
    moves and turns the whole sweep."""
    from omnire_synthetic.meshes import Mesh

    cube = Mesh.concat([
        quad([(10, -2, 0), (10, 2, 0), (10, 2, 4), (10, -2, 4)], 1, (1, 1)),  # near face, material 1
        quad([(14, -2, 0), (14, 2, 0), (14, 2, 4), (14, -2, 4)], 1, (1, 1)),
        quad([(10, -2, 4), (14, -2, 4), (14, 2, 4), (10, 2, 4)], 1, (1, 1)),
    ])
    g = _ground()
    verts = np.concatenate([g.verts, cube.verts])
    faces = np.concatenate([g.faces, cube.faces + len(g.verts)])
    mat = np.concatenate([g.mat, cube.mat])
    model = BeamModel(np.array([0.0, -20.0]), 0.5, 120.0)
    spec = LidarSpec(model, np.array([0.2, 0.9]), 89.0)
    # Sensor 5 m behind the origin and turned by 90 degrees: the box lies along its -y.
    pose = _sensor()
    pose[:3, :3] = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]
    pose[:3, 3] = [-5.0, 0.0, SENSOR_HEIGHT]
    sweep = cast_sweep(verts, faces, mat, pose, spec)
    level = (sweep.beam == 0) & sweep.returned
    az = np.deg2rad(sweep.column * 0.5)
    d_world = sweep.direction @ pose[:3, :3].T
    on_face = level & (d_world[:, 0] > 0) & (np.abs(15.0 * d_world[:, 1]) < (2.0 - 1e-6) * d_world[:, 0])
    assert on_face.sum() == 31  # |y| < 2 at x = 15 m: azimuths within 7.6 degrees, 0.5-degree steps
    np.testing.assert_allclose(sweep.range[on_face], 15.0 / np.abs(np.sin(az[on_face])), rtol=1e-12)
    assert (sweep.face[on_face] >= len(g.faces)).all()
    np.testing.assert_allclose(sweep.intensity[on_face], 0.9 * (0.3 + 0.7 * d_world[on_face, 0]), rtol=1e-6)
    assert not (level & ~on_face).any()  # the level beam meets nothing else (ground is below it)


def test_generation_is_deterministic(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    for p, seed in ((a, 1), (b, 1), (c, 2)):
        generate(p, "highway", SynthOptions(seed=seed, **TINY))
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)


def test_presets_contents():
    times = np.arange(8) / 10.0
    tmpl = load_template()
    kinds = {}
    for name, spec in PRESETS.items():
        ego = ego_trajectory(spec, times)
        actors = build_actors(spec, np.random.default_rng(0), times, ego, tmpl)
        kinds[name] = [a.kind for a in actors]
    assert set(kinds["urban"]) == {"car", "pedestrian", "cyclist"}
    assert set(kinds["highway"]) == {"car"}
    assert kinds["empty"] == []
    assert kinds["crowd"].count("pedestrian") >= 20


def test_crowd_crossers_walk_across_the_road():
    spec = PRESETS["crowd"]
    times = np.arange(10) / 10.0
    ego = ego_trajectory(spec, times)
    actors = build_actors(spec, np.random.default_rng(0), times, ego, load_template())
    crossing = [a for a in actors if a.kind == "pedestrian" and abs(abs(a.poses[0, 1, 0]) - 1.0) < 1e-6]
    assert len(crossing) >= 10  # heading along +-y: across the street
    for a in crossing:
        step = a.poses[1:, :3, 3] - a.poses[:-1, :3, 3]
        assert np.abs(step[:, 0]).max() < 1e-9 and np.abs(step[:, 1]).min() > 0.05


def test_walker_mesh_is_lbs_of_true_pose():
    spec = PRESETS["urban"]
    times = np.arange(4) / 10.0
    tmpl = load_template()
    actors = build_actors(spec, np.random.default_rng(5), times, ego_trajectory(spec, times), tmpl)
    ped = next(a for a in actors if a.kind == "pedestrian")
    for t in range(4):
        out = lbs(tmpl, ped.global_orient[t], ped.body_pose[t], transl=ped.transl[t])
        np.testing.assert_allclose(ped.body_verts[t], out.vertices, atol=1e-4)
        # The box encloses the body and its centre is where the canonical origin lands.
        local = (ped.body_verts[t] - ped.poses[t, :3, 3]) @ ped.poses[t, :3, :3]
        assert (np.abs(local) <= ped.size / 2 + 1e-4).all()
        np.testing.assert_allclose(ped.global_orient[t] @ np.zeros(3) + ped.poses[t, :3, 3],
                                   ped.transl[t] + tmpl.joints[0] - ped.global_orient[t] @ tmpl.joints[0], atol=1e-9)
    # Gait: the legs actually move between frames.
    assert np.abs(ped.body_pose[0] - ped.body_pose[3]).max() > 0.05


def test_scene_files_and_ground_truth(tmp_path):
    out = tmp_path / "urban"
    summary = generate(out, "urban", SynthOptions(seed=4, pose_noise_deg=3.0, drop_pose_frames=0.25,
                                                 box_noise_yaw_deg=2.0, **TINY))
    assert summary["frames"] == 8 and summary["lidar_points_mean"] > 10000
    for sub in ("images", "sky_masks", "dynamic_masks/human", "fine_dynamic_masks/vehicle", "depth"):
        assert len(list((out / sub).iterdir())) == 8 * 3, sub
    assert len(list((out / "ego_pose").iterdir())) == 8
    img = read_image(out / "images" / "000_0.jpg")
    assert img.shape == (48, 72, 3)
    sky = read_image(out / "sky_masks" / "000_0.png")[..., 0]
    assert set(np.unique(sky)) <= {0, 255} and (sky[0] == 255).any() and (sky[-1] == 0).all()
    # Fine masks lie inside the coarse (box) masks.
    fine = read_image(out / "fine_dynamic_masks" / "all" / "004_0.png")[..., 0] > 0
    coarse = read_image(out / "dynamic_masks" / "all" / "004_0.png")[..., 0] > 0
    assert fine.any() and (fine & ~coarse).sum() <= 0.05 * fine.sum()
    meta = json.loads((out / "ground_truth.json").read_text())
    assert meta["noise"] == {"box_translation_m": 0.0, "box_yaw_deg": 2.0, "pose_deg": 3.0, "dropped_pose_fraction": 0.25}
    with np.load(out / "ground_truth.npz") as gt:
        err = np.linalg.norm(gt["body_pose_written"] - gt["body_pose_true"], axis=(-2, -1))
        assert 0.02 < err.mean() < 0.2  # ~3 degrees per axis
        assert not gt["pose_valid_written"].all()
        np.testing.assert_allclose(gt["box_poses_written"][:, :, :3, 3], gt["box_poses_true"][:, :, :3, 3])
        yaw_err = np.arctan2(gt["box_poses_written"][..., 1, 0], gt["box_poses_written"][..., 0, 0]) - \
            np.arctan2(gt["box_poses_true"][..., 1, 0], gt["box_poses_true"][..., 0, 0])
        yaw_err = (yaw_err + np.pi) % (2 * np.pi) - np.pi
        assert 0.5 < np.rad2deg(yaw_err).std() < 4.0
    # PandaSet style writes 5 float32 columns per LiDAR row.
    assert (out / "lidar" / "000.bin").stat().st_size % 20 == 0


def test_synth_command_and_dataparser(tmp_path):
    plugins = load_plugins(strict=True, entry_points=False, extra_modules=(synthetic_plugin,))
    out = tmp_path / "empty"
    assert plugins.commands.get("synth").main(["empty", str(out), "--tiny", "--seed", "3"], plugins) == 0
    info = json.loads((out / "instances" / "instances_info.json").read_text())
    assert info == {}
    cfg = plugins.dataparsers.get("synthetic").config_factory()
    cfg.data = tmp_path / "generated"
    cfg.preset = "highway"
    cfg.generator = SynthOptions(**TINY)
    scene = cfg.setup().parse()
    assert scene.num_frames == 8 and len(scene.cameras) == 3
    assert scene.tracks and all(t.category == "vehicle" for t in scene.tracks)
    assert not scene.human_poses


def test_train_command_line_reads_the_generator_options(tmp_path):
    """`omnire train <method> synthetic` parses (the reader's and the generator's --fps were
    one flag twice) and the scene's frame rate is the generator's."""
    from omnire.runconfig import parse_train_args

    plugins = load_plugins()
    config = parse_train_args(["3dgs", "synthetic", "--data", str(tmp_path / "s"), "--preset", "empty",
                               "--frames", "3", "--width", "32", "--height", "24", "--fps", "5"], plugins)
    assert config.dataparser.generator.fps == 5.0 and config.dataparser.generator.frames == 3
    scene = config.dataparser.setup().parse()
    assert np.allclose(np.diff(scene.frame_timestamps), 0.2)


def test_output_folder_rules(tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    try:
        generate(other, "empty", SynthOptions(frames=1, width=16, height=12))
    except FileExistsError as exc:
        assert "other" in str(exc)
    else:
        raise AssertionError("wrote into a foreign non-empty folder")
    # Regenerating in another style replaces the old scene (no stale per-camera extrinsics).
    out = tmp_path / "scene"
    generate(out, "empty", SynthOptions(frames=2, width=16, height=12, style="waymo"))
    assert (out / "extrinsics" / "0.txt").is_file()
    generate(out, "empty", SynthOptions(frames=2, width=16, height=12, style="pandaset"))
    assert not (out / "extrinsics" / "0.txt").exists() and (out / "extrinsics" / "000_0.txt").is_file()


def test_missing_returns_recovered_from_a_ray_traced_street():
    """omnire.beams on a ray-traced sweep of the urban street (buildings, cars, sky): the
    returns alone give back each one's beam, the azimuth step, and the range image whose
    "no return" cells are exactly the rays the caster dropped (sky, range, grazing)."""
    from omnire.beams import assign_beams, estimate_azimuth_resolution, range_image, spherical
    from omnire_synthetic.textures import build_textures
    from omnire_synthetic.world import LIDAR_HEIGHT, build_static

    spec = PRESETS["urban"]
    times = np.arange(2) / 10.0
    ego = ego_trajectory(spec, times)
    static = build_static(spec, np.random.default_rng(0), -40.0, 160.0)
    model = BeamModel(np.linspace(-25.0, 10.0, 32), 0.4, 60.0, 0.3)
    sensor = ego[1].copy()
    sensor[2, 3] += LIDAR_HEIGHT
    sweep = cast_sweep(static.verts, static.faces, static.mat, sensor, LidarSpec(model, build_textures(0)[1]))
    ok = sweep.returned
    assert 0.3 < ok.mean() < 0.95 and {NOTHING_HIT, OUT_OF_RANGE, GRAZING} <= set(np.unique(sweep.reason))
    r, az, el = spherical(sweep.points_sensor())
    np.testing.assert_allclose(r, sweep.range[ok], rtol=1e-9)
    beams = assign_beams(el, model)
    np.testing.assert_array_equal(beams, sweep.beam[ok])
    assert estimate_azimuth_resolution(az, beams) == pytest.approx(0.4, abs=1e-6)
    image = range_image(r, az, beams, model)
    assert image.collisions == 0
    np.testing.assert_array_equal(image.returned, ok.reshape(model.num_beams, model.num_azimuths))
    np.testing.assert_allclose(image.range[image.returned], sweep.range[ok], rtol=1e-6)
