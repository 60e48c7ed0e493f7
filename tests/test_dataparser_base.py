"""What every dataparser shares (omnire/data/dataparser.py, omnire.pointcloud.thin_points):
checked against obvious implementations, the shared option checks through the real CLI, and
the old flag name --max-box-gap still loading."""
from __future__ import annotations

import numpy as np
import pytest

from omnire.api import (
    ConfigError,
    LogDataparserConfig,
    hold_absent_poses,
    is_stationary,
    loaded_intrinsics,
    majority_label,
    nearest_index,
    resample_track,
    rot_z,
    thin_points,
)
from hostile import run_case


def test_thin_points_is_a_seeded_ordered_subset():
    pts = np.arange(300, dtype=np.float64).reshape(100, 3)
    a = thin_points(pts, 10, 1234)
    assert a.shape == (10, 3) and np.array_equal(a, thin_points(pts, 10, 1234))  # same key, same points
    rows = a[:, 0] / 3
    assert np.all(np.diff(rows) > 0) and set(rows.astype(int)) <= set(range(100))  # distinct, original order
    assert not np.array_equal(a, thin_points(pts, 10, 1235))  # another sweep, another draw
    assert thin_points(pts, 0, 1) is pts and thin_points(pts, 100, 1) is pts and thin_points(pts, 500, 1) is pts


def test_hold_absent_poses_against_a_loop():
    rng = np.random.default_rng(0)
    for _ in range(20):
        F = 12
        present = rng.random(F) < 0.4
        poses = rng.normal(size=(F, 4, 4))
        got = hold_absent_poses(poses, present)
        if not present.any():
            assert got is poses
            continue
        first = int(np.flatnonzero(present)[0])
        for f in range(F):
            earlier = [g for g in range(f + 1) if present[g]]
            assert np.array_equal(got[f], poses[earlier[-1] if earlier else first])


def test_resample_track_exact_interpolated_and_absent():
    times = np.array([0.0, 1.0, 3.0])
    boxes = np.tile(np.eye(4), (3, 1, 1))
    boxes[:, 0, 3] = [0.0, 2.0, 6.0]
    boxes[1, :3, :3] = rot_z(np.array(0.4))
    query = np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 4.0])
    poses, present = resample_track(times, boxes, query, max_gap=1.5)
    assert present.tolist() == [False, True, True, True, False, True, False]  # 1 -> 3 is a 2 s gap
    assert np.array_equal(poses[[1, 3, 5]], boxes)  # annotated times exactly
    assert np.isclose(poses[2, 0, 3], 1.0)  # halfway in x
    assert np.allclose(poses[2, :3, :3], rot_z(np.array(0.2)), atol=1e-12)  # halfway in yaw
    assert np.array_equal(poses[0], boxes[0]) and np.array_equal(poses[4], boxes[1])  # held, finite
    assert resample_track(times, boxes, query, max_gap=0.0)[1].tolist() == [False, True, False, True, False, True,
                                                                              False]


def test_is_stationary_is_the_net_motion_of_the_medians():
    rng = np.random.default_rng(1)
    parked = np.array([5.0, 2.0, 0.8]) + rng.normal(scale=0.1, size=(60, 3))  # 0.1 m jitter
    assert is_stationary(parked) and is_stationary(parked[:1]) and is_stationary(parked[:0])
    driving = np.stack([np.linspace(0, 3, 30), np.zeros(30), np.zeros(30)], 1)
    assert not is_stationary(driving)
    # Slower obvious version: sorted thirds, medians, distance.
    for n in (2, 3, 7, 31):
        c = rng.normal(size=(n, 3))
        k = max(1, n // 3)
        net = np.linalg.norm(np.median(c[n - k:], 0) - np.median(c[:k], 0))
        assert is_stationary(c, net + 1e-9) and not is_stationary(c, net)


def test_nearest_index_matches_brute_force():
    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 50):
        times = np.sort(rng.choice(10_000, n, replace=False)).astype(np.int64)
        query = rng.integers(-500, 10_500, 200)
        query[:n] = times  # exact hits
        query[n:2 * n - 1] = (times[:-1] + times[1:]) // 2 if n > 1 else query[n:2 * n - 1]  # (near-)ties
        brute = np.array([int(np.argmin(np.abs(times - q))) for q in query])  # argmin: the earlier on ties
        assert np.array_equal(nearest_index(times, query), brute)
    assert nearest_index(np.array([0.0, 10.0]), np.array([5.0])).tolist() == [0]  # an exact tie: the earlier


def test_majority_label_ties_go_to_the_first_name():
    assert majority_label(["Car", "Van", "Car"]) == "Car"
    assert majority_label(["Van", "Car", "Car", "Van"]) == "Car"
    assert majority_label(np.array(["b", "a"], dtype=object)) == "a"


@pytest.mark.parametrize("centres", ["half", "integer"])
def test_loaded_intrinsics_against_projection(centres):
    """A point projected with the file's K, turned into continuous coordinates (+0.5 for
    integer centres) and scaled with the image, lands where the loaded K projects it."""
    K = np.array([[500.0, 1.5, 319.2], [0.0, 480.0, 241.7], [0.0, 0.0, 1.0]])
    W, H, Kl = loaded_intrinsics(K, 640, 481, 0.3, centres)
    assert (W, H) == (192, 144)  # round(640 * 0.3), round(481 * 0.3)
    p = np.array([[0.3, -0.2, 4.0], [-1.0, 0.7, 9.0]])
    uv_file = (p @ K.T)[:, :2] / p[:, 2:]
    uv_cont = uv_file + (0.5 if centres == "integer" else 0.0)
    expected = uv_cont * [W / 640, H / 481]
    got = (p @ Kl.T)[:, :2] / p[:, 2:]
    assert np.allclose(got, expected, atol=1e-12)
    assert loaded_intrinsics(K, 3, 3, 0.01)[:2] == (1, 1)


def test_shared_option_checks():
    for kw, needle in [({"scale": 0.0}, "scale: 0.0, expected a positive number"),
                       ({"scale": float("nan")}, "scale: nan"),
                       ({"max_lidar_points_per_frame": -1}, "max_lidar_points_per_frame: -1"),
                       ({"max_track_gap": -0.5}, "max_track_gap: -0.5"),
                       ({"max_track_gap": float("nan")}, "max_track_gap: nan"),
                       ({"stationary_threshold": -1.0}, "stationary_threshold: -1.0"),
                       ({"cameras": ("a", "b", "a")}, "lists a camera twice")]:
        with pytest.raises(ConfigError, match=needle.replace("(", r"\(")):
            LogDataparserConfig(**kw).check()
    LogDataparserConfig().check()


@pytest.mark.parametrize("reader", ["kitti", "nuscenes", "nuplan", "argoverse2", "waymo", "pandaset", "processed"])
def test_bad_scale_is_one_line_from_every_reader(reader, tmp_path, capsys):
    run_case(f"{reader} --scale 0", ["train", "3dgs", reader, "--data", str(tmp_path), "--scale", "0",
                                     "--trainer.output-dir", str(tmp_path / "runs")], capsys, [tmp_path],
             needles=("scale: 0.0, expected a positive number",), surface=reader)


def test_old_flag_name_max_box_gap_still_parses():
    """Runs recorded before the rename carry --max-box-gap in run.json's argv."""
    from omnire.plugins import load_plugins
    from omnire.runconfig import parse_train_args

    plugins = load_plugins()
    for reader in ("kitti", "nuscenes"):
        old = parse_train_args(["3dgs", reader, "--max-box-gap", "0.8"], plugins)
        new = parse_train_args(["3dgs", reader, "--max-track-gap", "0.8"], plugins)
        assert old.dataparser.max_track_gap == new.dataparser.max_track_gap == 0.8
