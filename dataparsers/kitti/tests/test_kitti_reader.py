"""KITTI tracking reader on a synthetic multi-frame sequence written in the KITTI layout:
round trip against the processed reader and the ground truth, the devkit's conventions
checked independently (Mercator poses, label boxes), stereo geometry, errors, and a short
`omnire train` run."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from omnire.api import ConfigError, interpolate_track, range_image, spherical
from omnire_kitti import (
    KittiConfig,
    KittiDataError,
    KittiFileMissing,
    category_of,
    label_box,
    oxts_poses,
    read_calib,
)
from omnire_kitti import hdl64e
from omnire_kitti.writer import CAMERA_T, HDL64E_LIKE_ELEVATIONS_DEG, VELODYNE_AXES, scan_order, write_kitti

FRAMES = 10
AZIMUTH_STEP = 0.5
"""Azimuth step (degrees) of the synthetic sweeps (not twice the Velodyne's 0.4 degree
mounting yaw, so each beam's firing azimuths sit clear of a column boundary)."""


def parse(data: Path, **kw):
    return KittiConfig(data=data, scale=1.0, **kw).setup().parse()


def read_rgb(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    px = np.asarray(inp.read_image(0, 0, 0, 3, oiio.UINT8)).reshape(spec.height, spec.width, 3)
    inp.close()
    return px


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from omnire_processed.reader import ProcessedDataparser, ProcessedDataparserConfig
    from omnire_synthetic.generate import SynthOptions, generate

    root = tmp_path_factory.mktemp("kitti")
    proc = root / "processed"
    # Waymo style: 14-column LiDAR with intensity on Waymo's unbounded scale, per-camera extrinsics;
    # the sweeps cast at an HDL-64E's 64 uneven elevations.
    generate(proc, "urban", SynthOptions(frames=FRAMES, width=64, height=40, num_cameras=1, style="waymo",
                                         lidar_elevations_deg=HDL64E_LIKE_ELEVATIONS_DEG,
                                         lidar_azimuth_step_deg=AZIMUTH_STEP, write_depth=False))
    out = root / "kitti"
    out.mkdir()
    summary = write_kitti(proc, out)
    reader = ProcessedDataparser(ProcessedDataparserConfig(data=proc, scale=1.0, holdout_every=0, load_human_poses=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = reader.parse()
    with np.load(proc / "ground_truth.npz") as z:
        gt = {k: z[k] for k in z.files}
    ego = gt["ego_to_world"]
    M = np.linalg.inv(ego[0]) @ np.linalg.inv(reader.world_from_file @ gt["file_from_generator"])
    return SimpleNamespace(proc=proc, out=out, split=out / "training", summary=summary, ref=ref, gt=gt, M=M,
                           scene=parse(out))


def copy_split(synth, tmp_path: Path) -> Path:
    dst = tmp_path / "kitti" / "training"
    shutil.copytree(synth.split, dst)
    return dst.parent


# ---------------------------------------------------------------------------- conventions
def test_oxts_mercator_matches_devkit_geometry():
    """1e-4 degrees of longitude at latitude 49 is cos(49 deg) * 6378137 * pi / 180 * 1e-4 m east;
    of latitude, 6378137 * pi / 180 * 1e-4 m north (Mercator with the first row's scale)."""
    rows = np.zeros((3, 30))
    rows[:, 0], rows[:, 1], rows[:, 2] = 49.0, 8.4, 110.0
    rows[1, 1] += 1e-4
    rows[2, 0] += 1e-4
    rows[2, 5] = np.pi / 2  # heading north
    P = oxts_poses(rows)
    step = 6378137.0 * np.pi / 180.0 * 1e-4
    assert np.allclose(P[1, :3, 3] - P[0, :3, 3], [np.cos(np.deg2rad(49.0)) * step, 0, 0], atol=1e-6)
    assert np.allclose(P[2, :3, 3] - P[0, :3, 3], [0, step, 0], atol=2e-4)
    assert np.allclose(P[0, :3, :3], np.eye(3)) and np.allclose(P[2, :3, 0], [0, 1, 0])  # yaw 0 = east, CCW


def test_label_box_matches_devkit_corners():
    """The box corners equal the devkit's: Ry(ry) @ [x: +-l/2, y: 0 or -h, z: +-w/2] + location."""
    h, w, l, x, y, z, ry = 1.5, 1.7, 4.2, 2.0, 1.6, 14.0, 0.3
    c, s = np.cos(ry), np.sin(ry)
    Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    xc = l / 2 * np.array([1, 1, -1, -1, 1, 1, -1, -1])
    yc = np.array([0, 0, 0, 0, -h, -h, -h, -h])
    zc = w / 2 * np.array([1, -1, -1, 1, 1, -1, -1, 1])
    devkit = (Ry @ np.stack([xc, yc, zc])).T + [x, y, z]
    T = label_box(h, w, l, x, y, z, ry)
    ours = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * [l / 2, w / 2, h / 2]
    ours = ours @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(np.sort(ours, axis=0), np.sort(devkit, axis=0))
    assert np.allclose(sorted(map(tuple, ours.round(9))), sorted(map(tuple, devkit.round(9))))
    assert np.allclose(T[:3, 0], [c, 0, -s]) and np.allclose(T[:3, 2], [0, -1, 0])  # heading; z up = -y camera
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_calib_keys_of_both_benchmarks(synth, tmp_path):
    ours = read_calib(synth.split / "calib" / "0000.txt")
    text = (synth.split / "calib" / "0000.txt").read_text()
    for a, b in (("R_rect ", "R0_rect: "), ("Tr_velo_cam ", "Tr_velo_to_cam: "), ("Tr_imu_velo ", "Tr_imu_to_velo: ")):
        text = text.replace(a, b)
    (tmp_path / "c.txt").write_text(text)
    other = read_calib(tmp_path / "c.txt")
    assert all(np.array_equal(ours[k], other[k]) for k in ours)


# ---------------------------------------------------------------------------- round trip
def test_camera_geometry(synth):
    s, ref = synth.scene, synth.ref
    assert s.num_frames == FRAMES and [c.name for c in s.cameras] == ["image_02"]
    cam = s.cameras[0]
    expected = synth.M[None] @ ref.cameras[0].cam_to_world  # the synthetic (pitched) front camera
    assert np.allclose(cam.cam_to_world[:, :3, 3], expected[:, :3, 3], atol=1e-8)  # same centre
    assert np.allclose(cam.cam_to_world[:, :3, :3], expected[:, :3, :3] @ synth.summary["R_rect"].T, atol=1e-9)
    assert np.allclose(cam.cam_to_world[:, :3, 1], [0, 0, -1], atol=1e-9)  # rectified: level, image y = down
    assert np.allclose(cam.intrinsics, synth.summary["K_rect"], rtol=1e-11)
    assert (cam.width, cam.height) == (64, 40) and cam.distortion is None
    assert np.allclose(s.frame_timestamps, np.arange(FRAMES) / 10) and np.array_equal(cam.timestamps, s.frame_timestamps)
    assert np.allclose(s.ego_poses, np.linalg.inv(synth.gt["ego_to_world"][0])[None] @ synth.gt["ego_to_world"],
                       atol=1e-6)


def test_rectified_image_content(synth):
    """LiDAR points land on the same colours in image_02 (resampled) and the synthetic camera."""
    s, ref = synth.scene, synth.ref
    diffs = []
    for f in (0, FRAMES - 1):
        pts = s.lidar.points[f].astype(np.float64)
        samples = []
        for cam, c2w in ((s.cameras[0], s.cameras[0].cam_to_world[f]),
                         (ref.cameras[0], synth.M @ ref.cameras[0].cam_to_world[f])):
            w2c = np.linalg.inv(c2w)
            pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
            uv = pc @ cam.intrinsics.T
            uv = uv[:, :2] / np.maximum(uv[:, 2:], 1e-9)
            samples.append((uv, pc[:, 2], read_rgb(cam.image_paths[f]).astype(float)))
        (uv_a, z_a, im_a), (uv_b, z_b, im_b) = samples
        ok = (z_a > 2) & (z_b > 2)
        for uv in (uv_a, uv_b):
            ok &= (uv[:, 0] > 2) & (uv[:, 0] < 62) & (uv[:, 1] > 2) & (uv[:, 1] < 38)
        a = im_a[uv_a[ok, 1].astype(int), uv_a[ok, 0].astype(int)]
        b = im_b[uv_b[ok, 1].astype(int), uv_b[ok, 0].astype(int)]
        assert ok.sum() > 200
        diffs.append((np.median(np.abs(a - b)), np.mean(np.abs(a - b))))
    # a 3-pixel misregistration gives a median of ~10 and a mean of ~22 levels here
    assert max(d[0] for d in diffs) <= 5 and max(d[1] for d in diffs) < 13, diffs


def test_lidar_round_trip(synth):
    s, ref = synth.scene, synth.ref
    stored = {}  # frame -> the processed sweep's order of the KITTI file's returns
    for f in range(FRAMES):
        expected = ref.lidar.points[f].astype(np.float64) @ synth.M[:3, :3].T + synth.M[:3, 3]
        V = s.lidar.sensor_to_world[f]
        stored[f] = scan_order((expected - V[:3, 3]) @ V[:3, :3])
        assert s.lidar.points[f].shape == expected.shape
        assert np.abs(s.lidar.points[f] - expected[stored[f]]).max() < 5e-5
    origins = ref.lidar.origins @ synth.M[:3, :3].T + synth.M[:3, 3]
    assert np.allclose(s.lidar.origins, origins, atol=1e-6)
    for f in s.lidar.available_frames():  # reflectance is the intensity; the pose is the Velodyne's
        assert s.lidar.intensity[f].dtype == np.float32 and 0 <= s.lidar.intensity[f].min() <= s.lidar.intensity[f].max() <= 1
        np.testing.assert_allclose(s.lidar.intensity[f], ref.lidar.intensity[f][stored[f]], atol=1e-6)
        np.testing.assert_allclose(s.lidar.sensor_to_world[f][:3, 3], s.lidar.origins[f])
        assert s.lidar.sensor_to_world[f][:3, 0] @ s.ego_poses[f][:3, 0] > 0.99  # Velodyne x = forward
    assert s.lidar.times is None


def _cast_beam(elevation_deg: np.ndarray) -> np.ndarray:
    """(N,) Velodyne-frame elevations of synthetic returns -> (N,) index of the cast elevation
    (HDL64E_LIKE_ELEVATIONS_DEG) each lies on (exact ray casts stored as float32: checked
    within 0.01 degrees, far below the 0.27 degree smallest spacing)."""
    truth = np.array(HDL64E_LIKE_ELEVATIONS_DEG)
    beam = np.abs(elevation_deg[:, None] - truth[None]).argmin(axis=1)
    assert np.abs(elevation_deg - truth[beam]).max() < 0.01
    return beam


def test_hdl64e_beams_measured_from_sweeps(synth):
    """The 64 uneven elevations, each return's beam and the azimuth step come back from the
    sweeps alone (the files hold x y z reflectance only, laser by laser from the top one)."""
    lidar = synth.scene.lidar
    model = lidar.beam_model
    assert model is not None and model.num_beams == 64 and model.max_range == 120.0
    assert "scan lines" in model.name
    np.testing.assert_allclose(model.elevations_deg, HDL64E_LIKE_ELEVATIONS_DEG, atol=0.05)  # top to bottom
    assert model.azimuth_resolution_deg == pytest.approx(AZIMUTH_STEP, abs=1e-9)
    for f in lidar.available_frames():
        rows = np.fromfile(synth.split / "velodyne" / "0000" / f"{f:06d}.bin", dtype="<f4").reshape(-1, 4)
        true_beam = _cast_beam(spherical(rows[:, :3].astype(np.float64))[2])
        assert lidar.beams[f].dtype == np.int16
        np.testing.assert_array_equal(lidar.beams[f], true_beam)


def test_scan_order_of_written_sweeps(synth):
    """The writer stores a scan as KITTI does: laser by laser from the top one, each by
    increasing azimuth; scan_lines reads the lasers back from that order alone."""
    for f in (0, FRAMES - 1):
        rows = np.fromfile(synth.split / "velodyne" / "0000" / f"{f:06d}.bin", dtype="<f4").reshape(-1, 4)
        el = spherical(rows[:, :3].astype(np.float64))[2]
        az = np.arctan2(rows[:, 1], rows[:, 0])  # from behind the car (-pi) round to behind it again
        cast = _cast_beam(el)
        assert np.all(np.diff(cast) >= 0) and np.all(np.diff(az)[np.diff(cast) == 0] > 0)
        np.testing.assert_array_equal(hdl64e.scan_lines(rows[:, :3]), cast)
    with pytest.raises(ValueError, match=r"scan_lines: points \(5, 4\), expected \(N, 3\)"):
        hdl64e.scan_lines(np.zeros((5, 4)))


def _offset_laser_sweep(azimuth_step: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """One HDL-64E-like revolution whose lasers sit off the optical centre, as a real unit's
    do, cast analytically: (N, 3) returns in KITTI's order and (N,) the laser of each.

    Laser b fires from (0, 0, h_b) at elevation HDL64E_LIKE_ELEVATIONS_DEG[b] (h_b about
    0.15 m in the upper block, 0.05 m in the lower, as a real KITTI scan's lines fit); the
    scene is flat ground 1.73 m below the centre and a 3 m high wall at a horizontal distance
    that varies with azimuth between 6 and 40 m (beyond its top: nothing)."""
    rng = np.random.default_rng(3)
    el = np.deg2rad(np.array(HDL64E_LIKE_ELEVATIONS_DEG))
    h = np.concatenate([rng.uniform(0.11, 0.21, 32), rng.uniform(0.03, 0.07, 32)])
    az = np.deg2rad(np.arange(-180.0, 180.0, azimuth_step) + 0.1)
    E, A = np.meshgrid(el, az, indexing="ij")  # (64, A): laser-major, as KITTI stores them
    H = np.repeat(h[:, None], len(az), 1)
    wall = 6.0 + 34.0 * (0.5 + 0.5 * np.sin(3 * A))  # horizontal distance of the wall
    t_wall = wall / np.cos(E)
    z_wall = H + t_wall * np.sin(E)
    t_ground = np.where(E < 0, (-1.73 - H) / np.sin(np.minimum(E, -1e-9)), np.inf)
    t = np.where((z_wall <= 3.0) & (t_wall < t_ground), t_wall, t_ground)
    hit = np.isfinite(t) & (t < 120.0)
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1)
    p = d * t[..., None]
    p[..., 2] += H
    laser = np.repeat(np.arange(64)[:, None], len(az), 1)
    return p[hit], laser[hit]


def test_lasers_off_the_optical_centre_need_the_file_order():
    """With lasers 3-21 cm off the optical centre (a real HDL-64E), near returns' apparent
    elevations stray by more than the spacing between lasers: the elevations alone are
    refused, the file order gives every return its laser."""
    sweeps = [_offset_laser_sweep() for _ in range(3)]
    points = [p for p, _ in sweeps]
    poses = np.repeat(np.eye(4)[None], 3, 0)
    el = spherical(points[0])[2]
    far = np.linalg.norm(points[0], axis=1) > hdl64e.MIN_RANGE_M
    stray = np.abs(el - np.array(HDL64E_LIKE_ELEVATIONS_DEG)[sweeps[0][1]])[far]
    assert np.percentile(stray, 90) > 0.3  # the offsets matter (about h / d)
    by_elevation = hdl64e.measure_beams(points, poses)
    assert by_elevation.model is None and by_elevation.reason.startswith("file order: no scan lines given; elevations:")
    fit = hdl64e.measure_beams(points, poses, [hdl64e.scan_lines(p) for p in points])
    assert fit.model is not None and fit.reason == ""
    for (_, laser), beams in zip(sweeps, fit.beams):
        np.testing.assert_array_equal(beams, laser)
    assert np.all(np.diff(fit.model.elevations_deg) < 0)  # the lines' medians, top to bottom
    assert fit.model.azimuth_resolution_deg == pytest.approx(0.5, abs=1e-9)
    with pytest.raises(ValueError, match=r"sweep 1 has \d+ returns and scan lines of shape \(3,\)"):
        hdl64e.measure_beams(points, poses, [hdl64e.scan_lines(points[0]), np.zeros(3), None])


def test_missing_returns_recovered_on_beam_grid(synth):
    """On the measured beam grid every return has a cell of its own, on its cast beam's row
    and its cast azimuth's column (up to one shift per row: column 0 is a beam's first
    firing), so the empty cells are exactly the rays that returned nothing."""
    lidar = synth.scene.lidar
    model = lidar.beam_model
    A = model.num_azimuths
    yaw = np.rad2deg(np.arctan2(VELODYNE_AXES[1, 0], VELODYNE_AXES[0, 0]))  # cast azimuth = Velodyne's + yaw
    for f in lidar.available_frames():
        M = lidar.sensor_to_world[f]
        r, az, el = spherical((lidar.points[f].astype(np.float64) - M[:3, 3]) @ M[:3, :3])
        image = range_image(r, az, lidar.beams[f], model)
        rows, cols = np.nonzero(image.returned)
        idx = image.point[rows, cols]
        assert image.collisions == 0 and len(idx) == len(r)
        assert (_cast_beam(el)[idx] == rows).all()
        shift = (np.round(((az[idx] + yaw) % 360.0) / AZIMUTH_STEP).astype(np.int64) - cols) % A
        assert all(len(np.unique(shift[rows == b])) == 1 for b in np.unique(rows))
        np.testing.assert_allclose(image.range[rows, cols], r[idx], rtol=1e-6)
        assert (~image.returned).sum() == 64 * A - len(r) > 0  # the missing returns (sky, range, grazing)


def test_shuffled_scans_fall_back_to_elevations(synth, tmp_path):
    """Scans stored in another order give no scan lines; the elevations still give every
    return its laser (the synthetic lasers sit at the optical centre)."""
    root = copy_split(synth, tmp_path)
    rng = np.random.default_rng(0)
    for path in sorted((root / "training" / "velodyne" / "0000").glob("*.bin")):
        rows = np.fromfile(path, dtype="<f4").reshape(-1, 4)
        path.write_bytes(rows[rng.permutation(len(rows))].tobytes())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = parse(root)
    assert not [w for w in caught if "beams" in str(w.message)]
    assert s.lidar.beam_model is not None and "elevations measured from the sweeps" in s.lidar.beam_model.name
    for f in s.lidar.available_frames():
        M = s.lidar.sensor_to_world[f]
        el = spherical((s.lidar.points[f].astype(np.float64) - M[:3, 3]) @ M[:3, :3])[2]
        np.testing.assert_array_equal(s.lidar.beams[f], _cast_beam(el))


@pytest.mark.parametrize("damage, reason", [
    ("continuous", r"file order: loaded sweep 0 holds \d+ scan lines, expected 64; elevations: .*"
                   "(deg of their beam's elevation|not one of 64 lasers)"),
    ("half_the_lasers", r"file order: loaded sweep 0 holds 32 scan lines, expected 64; elevations: .*"
                        r"found \d+ elevation peaks, expected 64"),
])
def test_untrusted_beams_warn_once(synth, tmp_path, damage, reason):
    """Sweeps whose order and elevations both fail to give 64 beams load without beams, with
    one warning naming the folder and both reasons; --no-estimate-beams skips the measurement."""
    root = copy_split(synth, tmp_path)
    rng = np.random.default_rng(0)
    for path in sorted((root / "training" / "velodyne" / "0000").glob("*.bin")):
        rows = np.fromfile(path, dtype="<f4").reshape(-1, 4)
        if damage == "continuous":  # order lost, elevations spread over +-3 degrees of their beams
            rows = rows[rng.permutation(len(rows))]
            rows[:, 2] += rng.uniform(-0.05, 0.05, len(rows)) * np.linalg.norm(rows[:, :2], axis=1)
        else:  # a 32-laser sensor: every other beam's returns removed
            rows = rows[_cast_beam(spherical(rows[:, :3].astype(np.float64))[2]) % 2 == 0]
        path.write_bytes(rows.astype("<f4").tobytes())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = parse(root)
    notes = [str(w.message) for w in caught if "get no beams" in str(w.message)]
    assert len(notes) == 1, notes
    assert re.search(r"velodyne/0000: the sweeps get no beams: .*(" + reason + ")", notes[0]), notes[0]
    assert s.lidar.beams is None and s.lidar.beam_model is None and s.lidar.points[0] is not None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        off = parse(root, estimate_beams=False)
    assert not [w for w in caught if "beams" in str(w.message)] and off.lidar.beams is None


def test_boxes_round_trip(synth):
    s, ref = synth.scene, synth.ref
    labels = np.loadtxt(synth.split / "label_02" / "0000.txt", dtype=str, ndmin=2)
    mine = {t.track_id: t for t in s.tracks}
    ids = list(synth.gt["track_ids"])
    t = s.frame_timestamps
    checked = 0
    for tr in ref.tracks:
        tid = str(ids.index(tr.track_id))
        rows = labels[labels[:, 1] == tid]
        if not len(rows):
            assert tid not in mine
            continue
        m = mine[tid]
        labelled = rows[:, 0].astype(int)
        assert tr.present[labelled].all()
        _, expected_present = interpolate_track(t[labelled], np.tile(np.eye(4), (len(labelled), 1, 1)),
                                                np.ones(len(labelled), bool), t, max_gap=0.5)
        assert np.array_equal(m.present, expected_present)
        poses = synth.M[None] @ tr.poses
        assert np.allclose(m.poses[labelled, :3, 3], poses[labelled, :3, 3], atol=1e-5)
        assert np.allclose(m.poses[labelled, :3, :3], poses[labelled, :3, :3], atol=2e-6)
        assert np.allclose(m.size, tr.size, atol=1e-6)
        assert m.class_name in ("Car", "Pedestrian", "Cyclist") and m.category == category_of(m.class_name)
        checked += 1
    assert checked >= 4


def test_dontcare_skipped_and_stereo(synth, tmp_path):
    root = copy_split(synth, tmp_path)
    split = root / "training"
    lab = split / "label_02" / "0000.txt"
    lab.write_text("0 -1 DontCare -1 -1 -10.000000 219.310000 188.490000 245.500000 218.560000 -1000.000000 "
                   "-1000.000000 -1000.000000 -10.000000 -1.000000 -1.000000 -1.000000\n" + lab.read_text())
    shutil.copytree(split / "image_02", split / "image_03")  # geometry only: contents do not matter here
    s = parse(root, load_lidar=False)
    assert [c.name for c in s.cameras] == ["image_02", "image_03"]
    assert [t.track_id for t in s.tracks] == [t.track_id for t in synth.scene.tracks]
    left, right = s.cameras[0].cam_to_world, s.cameras[1].cam_to_world
    t2, t3 = np.array(CAMERA_T[2]), np.array(CAMERA_T[3])
    assert np.allclose(right[:, :3, :3], left[:, :3, :3])
    assert np.allclose(right[:, :3, 3] - left[:, :3, 3], left[:, :3, :3] @ (t2 - t3), atol=1e-9)  # ~0.53 m right
    assert np.allclose(np.linalg.norm(right[:, :3, 3] - left[:, :3, 3], axis=1), 0.532, atol=1e-3)
    only = parse(root, cameras=("image_03",), load_lidar=False, start_frame=2, end_frame=5, sequence="0")
    assert only.source_frames.tolist() == [2, 3, 4] and np.allclose(only.ego_poses[0], np.eye(4), atol=1e-9)


def test_label_gaps_interpolated(synth, tmp_path):
    root = copy_split(synth, tmp_path)
    lab = root / "training" / "label_02" / "0000.txt"
    rows = [r.split() for r in lab.read_text().splitlines()]
    full = {t.track_id: t for t in synth.scene.tracks}
    a, b = [t.track_id for t in synth.scene.tracks if t.present.all()][:2]
    drop = {(a, "4")} | {(b, str(f)) for f in range(3, 9)}  # a: 0.2 s gap; b: 0.7 s gap
    lab.write_text("\n".join(" ".join(r) for r in rows if (r[1], r[0]) not in drop) + "\n")
    s = {t.track_id: t for t in parse(root, load_lidar=False).tracks}
    assert s[a].present.all()
    mid = s[a].poses[4]
    assert np.allclose(mid[:3, 3], (full[a].poses[3, :3, 3] + full[a].poses[5, :3, 3]) / 2, atol=1e-9)
    assert np.linalg.norm(mid[:3, 3] - full[a].poses[4, :3, 3]) < 0.05  # the true pose, nearly
    assert s[b].present.tolist() == [True] * 3 + [False] * 6 + [True]
    wide = {t.track_id: t for t in parse(root, load_lidar=False, max_track_gap=0.8).tracks}
    assert wide[b].present.all()


# ---------------------------------------------------------------------------- errors
def test_error_calib(synth, tmp_path):
    root = copy_split(synth, tmp_path)
    path = root / "training" / "calib" / "0000.txt"
    good = path.read_text()
    path.write_text("\n".join(l for l in good.splitlines() if not l.startswith("Tr_imu_velo")))
    with pytest.raises(KittiDataError, match=r"calib/0000\.txt: no Tr_imu_velo line \(also accepted: Tr_imu_to_velo\)"):
        parse(root)
    path.write_text(good.replace("R_rect 1.0", "R_rect x"))
    with pytest.raises(KittiDataError, match=r"R_rect has a non-numeric value; expected 9 numbers"):
        parse(root)
    path.write_text(good.replace("P2: ", "P2: 1.0 "))
    with pytest.raises(KittiDataError, match=r"P2 has 13 values, expected 12"):
        parse(root)


def test_error_oxts_and_labels(synth, tmp_path):
    root = copy_split(synth, tmp_path)
    oxts = root / "training" / "oxts" / "0000.txt"
    lines = oxts.read_text().splitlines()
    oxts.write_text("\n".join(lines[:3] + [" ".join(lines[3].split()[:12])] + lines[4:]))
    with pytest.raises(KittiDataError, match=r"oxts/0000\.txt: line 4 has 12 values, expected 30"):
        parse(root)
    oxts.write_text("\n".join(lines) + "\n")
    lab = root / "training" / "label_02" / "0000.txt"
    good = lab.read_text()
    lab.write_text(good + "3 7 Car 0 0 0.1 1 2 3 4 1.5 1.6\n")
    with pytest.raises(KittiDataError, match=r"label_02/0000\.txt: line \d+ has 12 columns, expected 17"):
        parse(root)
    lab.write_text(good + f"{FRAMES} 0 Car 0 0 0.1 1 2 3 4 1.5 1.6 4.0 0 1.6 10 -1.57\n")
    with pytest.raises(KittiDataError, match=rf"frame {FRAMES} outside the sequence's 0\.\.{FRAMES - 1}"):
        parse(root)
    lab.write_text(good + good.splitlines()[0] + "\n")
    with pytest.raises(KittiDataError, match=r"track \d+ appears twice in frame 0"):
        parse(root)


def test_error_files(synth, tmp_path):
    root = copy_split(synth, tmp_path)
    split = root / "training"
    (split / "image_02" / "0000" / "000003.png").unlink()
    with pytest.raises(KittiFileMissing, match=r"image_02/0000/000003\.png: missing image of image_02"):
        parse(root)
    assert parse(root, end_frame=3).num_frames == 3
    velo = split / "velodyne" / "0000" / "000001.bin"
    rows = np.fromfile(velo, dtype="<f4").reshape(-1, 4)
    rows[5, 3] = 1.5
    velo.write_bytes(rows.tobytes())
    with pytest.raises(KittiDataError, match=r"000001\.bin: column 4 \(reflectance\) must hold numbers in 0\.\.1 \(found 1\.5"):
        parse(root, end_frame=3)
    velo.write_bytes(velo.read_bytes()[:-4])
    with pytest.raises(KittiDataError, match=r"000001\.bin: \d+ bytes is not a whole number of 16-byte points"):
        parse(root, end_frame=3)
    velo.unlink()  # a missing scan is a gap (as in training sequence 0001)
    s = parse(root, end_frame=3)
    assert s.lidar.points[1] is None and np.isnan(s.lidar.origins[1]).all()
    with pytest.raises(KittiFileMissing, match=r"image_03/0000: missing \(cameras \['image_03'\] requested"):
        parse(root, cameras=("image_03",))
    with pytest.raises(ConfigError, match=r"cameras: \['image_01'\] are not KITTI colour cameras"):
        parse(root, cameras=("image_01",))
    with pytest.raises(ConfigError, match=r"sequence: 'abc'"):
        parse(root, sequence="abc")
    with pytest.raises(KittiFileMissing, match=r"calib/0004\.txt: missing calibration file"):
        parse(root, sequence="4")
    with pytest.raises(KittiFileMissing, match=r"testing: no such split folder .*\['training'\]"):
        parse(root, split="testing")
    with pytest.raises(KittiFileMissing, match="nowhere: KITTI tracking folder does not exist"):
        parse(tmp_path / "nowhere")
    (split / "label_02" / "0000.txt").unlink()  # testing-like: no labels, no actors
    assert parse(split, end_frame=3).tracks == []


def test_category_mapping():
    for label, cat in {"Car": "vehicle", "Van": "vehicle", "Truck": "vehicle", "Tram": "vehicle",
                       "Pedestrian": "human", "Person_sitting": "human", "Person": "human",
                       "Cyclist": "cyclist", "Misc": "other"}.items():
        assert category_of(label) == cat


# ---------------------------------------------------------------------------- plugin and CLI
def test_plugin_registered():
    from omnire.plugins import load_plugins

    plugins = load_plugins()
    assert "kitti" in plugins.dataparsers.names() and "kitti" in plugins.scene_writers.names()
    assert plugins.dataparsers.provenance("kitti").distribution == "omnire-dataparser-kitti"


def test_synth_format_and_train(tmp_path):
    from omnire.plugins import load_plugins
    from omnire_synthetic.cli import main as synth_main

    scene = tmp_path / "tiny_kitti"
    assert synth_main(["urban", str(scene), "--tiny", "--format", "kitti"], load_plugins()) == 0
    assert (scene / "training" / "calib" / "0000.txt").is_file()
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200")
    out = subprocess.run(
        [sys.executable, "-m", "omnire.cli", "train", "3dgs", "kitti", "--data", str(scene), "--scale", "1",
         "--trainer.max-steps", "3", "--trainer.no-progress", "--method.rasterizer", "torch",
         "--method.nodes.background.max-lidar-points", "2000", "--method.nodes.background.num-far-points", "200",
         "--trainer.output-dir", str(tmp_path / "runs")],
        capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "kitti_training_0000" in out.stdout
