"""The closed-loop building blocks against slower obvious implementations: the bicycle model
against the exact circle, box overlap against point sampling, the route projection against a
dense polyline search, the request checks and the JSON -> scenario tables."""
from __future__ import annotations

import math

import numpy as np
import pytest

from omnire_serve.bicycle import BicycleLimits, EgoState, advance, track_waypoints
from omnire_serve.boxes import footprint, overlap
from omnire_serve.checks import Limits, image_size, pose_matrix
from omnire_serve.corridor import Corridor, build_corridor
from omnire_serve.errors import RequestError
from omnire_serve.tables import parse_tables, tables_to_toml


def test_bicycle_follows_the_exact_circle():
    """Constant speed and steering angle: the reference point runs on a circle of radius
    L / tan(steer); the midpoint integration matches the closed form (float64)."""
    lim = BicycleLimits(wheelbase=2.8)
    st = EgoState(1.0, -2.0, 0.3, 6.0, 0.2)
    R = lim.wheelbase / math.tan(0.2)
    out = st
    for _ in range(20):
        out = advance(out, 0.0, 0.0, 0.1, lim)
    omega = 6.0 / R
    T = 2.0
    cx, cy = 1.0 - R * math.sin(0.3), -2.0 + R * math.cos(0.3)
    yaw = 0.3 + omega * T
    assert out.x == pytest.approx(cx + R * math.sin(yaw), abs=1e-4)
    assert out.y == pytest.approx(cy - R * math.cos(yaw), abs=1e-4)
    assert out.yaw == pytest.approx(yaw, abs=1e-6)


def test_bicycle_limits_and_stops():
    lim = BicycleLimits()
    st = advance(EgoState(0, 0, 0, 1.0, 0), -100.0, 0.0, 1.0, lim)
    assert st.speed == 0.0  # braked to a stop, never reversing
    assert st.x == pytest.approx(1.0 / (2 * lim.max_brake), abs=1e-9)  # v^2 / 2a, at the strongest braking
    st = advance(EgoState(0, 0, 0, 1.0, 0), 0.0, 100.0, 1.0, lim)
    assert st.steer == pytest.approx(lim.max_steer)  # held at the bound
    with pytest.raises(ValueError):
        advance(st, float("nan"), 0.0, 0.1)


def test_waypoints_straight_ahead_keep_speed():
    st = EgoState(0, 0, 0, 5.0, 0.0)
    wp = np.array([[0.5 * (k + 1), 0.0] for k in range(4)])
    accel, rate = track_waypoints(st, wp, 0.1)
    assert accel == pytest.approx(0.0) and rate == pytest.approx(0.0)


def test_overlap_matches_point_sampling():
    rng = np.random.default_rng(0)
    for _ in range(120):
        a = footprint(rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 5), rng.uniform(0.5, 3))
        b = footprint(rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 5), rng.uniform(0.5, 3))
        g = np.stack(np.meshgrid(np.linspace(-7, 7, 201), np.linspace(-7, 7, 201)), -1).reshape(-1, 2)

        def inside(poly):
            edges = np.roll(poly, -1, 0) - poly
            cross = edges[None, :, 0] * (g[:, None, 1] - poly[None, :, 1]) - edges[None, :, 1] * (g[:, None, 0] - poly[None, :, 0])
            return np.all(cross >= -1e-9, axis=1) | np.all(cross <= 1e-9, axis=1)

        sampled = bool(np.any(inside(a) & inside(b)))
        if sampled:  # sampling finds overlap only where there is some
            assert overlap(a, b)
        elif overlap(a, b):  # an overlap thinner than the grid: the boxes nearly touch
            grown = footprint(a.mean(0), math.atan2(*(a[0] - a[1])[::-1]), np.linalg.norm(a[0] - a[1]) + 0.3,
                              np.linalg.norm(a[0] - a[3]) + 0.3)
            assert np.any(inside(grown) & inside(b))


def test_route_projection_matches_dense_search():
    xy = np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 3.0], [14.0, 9.0]])
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    c = Corridor(xy, s, np.full(4, 2.0), np.full(4, 2.0), np.zeros(4))
    dense_s = np.linspace(0, s[-1], 200001)
    dense = np.stack([np.interp(dense_s, s, xy[:, 0]), np.interp(dense_s, s, xy[:, 1])], 1)
    rng = np.random.default_rng(1)
    for p in rng.uniform([-1, -3], [15, 10], (50, 2)):
        got_s, got_d = c.project(p)
        k = int(np.argmin(np.linalg.norm(dense - p, axis=1)))
        if 0.01 < got_s < s[-1] - 0.01:
            assert got_s == pytest.approx(dense_s[k], abs=2e-3)
            assert abs(got_d) == pytest.approx(np.linalg.norm(dense[k] - p), abs=2e-3)


def test_corridor_borders_stop_at_obstacles():
    """A straight road with a wall 2.5 m to the left and a low kerb 3 m to the right:
    the corridor ends at the wall and ignores the kerb (below obstacle_low)."""
    F = 20
    rig = np.tile(np.eye(4), (F, 1, 1))
    rig[:, 0, 3] = np.linspace(0, 19, F)
    rng = np.random.default_rng(2)
    road = np.c_[rng.uniform(-2, 22, 4000), rng.uniform(-4, 4, 4000), rng.normal(-1.5, 0.02, 4000)]
    wall = np.c_[rng.uniform(-2, 22, 2000), np.full(2000, 2.5), rng.uniform(-1.5, 1.0, 2000)]
    kerb = np.c_[rng.uniform(-2, 22, 1000), np.full(1000, -3.0), rng.uniform(-1.5, -1.35, 1000)]
    cloud = np.concatenate([road, wall, kerb])
    c = build_corridor(rig, [cloud] + [None] * (F - 1), [[] for _ in range(F)])
    assert np.allclose(c.ground, -1.5, atol=0.05)
    assert np.allclose(c.left, 2.5, atol=0.05)
    assert np.allclose(c.right, 3.5)  # capped at max_half_width
    assert c.length == pytest.approx(19.0)


def test_pose_checks_name_the_problem():
    extent = (np.zeros(3), np.ones(3) * 10)
    good = np.eye(4)
    assert pose_matrix(good.tolist(), "pose", extent, 5.0).shape == (4, 4)
    cases = {"NaN": [[float("nan")] * 4] * 4, "shape": [[1, 0], [0, 1]], "far": _translated(1000.0),
             "scaled": (np.diag([2.0, 1, 1, 1])).tolist(), "text": "eye"}
    for name, value in cases.items():
        with pytest.raises(RequestError) as err:
            pose_matrix(value, "pose", extent, 5.0)
        assert err.value.field == "pose", name


def _translated(x: float) -> list:
    P = np.eye(4)
    P[0, 3] = x
    return P.tolist()


def test_image_size_limits():
    lim = Limits(max_pixels=1000)
    assert image_size(None, None, (20, 10), lim) == (20, 10)
    for w, h, field in ((1000, 1000, "width"), (10, None, "height"), (0, 5, "width"), (1.5, 4, "width")):
        with pytest.raises(RequestError) as err:
            image_size(w, h, (20, 10), lim)
        assert err.value.field == field


def test_json_tables_parse_as_the_scenario_file_does(tmp_path):
    tables = {"actor": [{"track": "a", "stop_at": 1.5, "brake": 0.5},
                        {"track": "b", "trajectory": [{"t": 0.0, "x": 1.0, "y": 2.0}, {"t": 1.0, "x": 3.0, "y": 2.0}]}]}
    sc = parse_tables(tables, tmp_path)
    assert [a.track for a in sc.actors] == ["a", "b"]
    assert sc.actors[0].clock.stop_at == 1.5 and sc.actors[1].trajectory.waypoints[1].x == 3.0
    assert '"track" = "a"' in tables_to_toml(tables)
    for bad, field in (({"actor": [{"track": "a", "stop_at": float("nan")}]}, "actor.0.stop_at"),
                       ({"camera": {}}, "camera"), ({"actor": [{"track": "a", "speed": None}]}, "actor.0.speed"),
                       ({"actor": [{"track": "a", "bogus": 1}]}, "actor.0.bogus")):
        with pytest.raises(RequestError) as err:
            parse_tables(bad, tmp_path)
        assert err.value.field == field, (bad, err.value)


def test_gap_ahead_matches_sliding_the_ego_forward():
    """The gap to a box in the path equals how far the ego's footprint (widened by the
    margin) slides forward before it first touches the box, found in 1 cm steps."""
    from omnire_serve.boxes import footprint_of, gap_ahead

    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(200):
        yaw = rng.uniform(-np.pi, np.pi)
        pose = np.eye(4)
        a = rng.uniform(-np.pi, np.pi)
        pose[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        pose[:2, 3] = rng.uniform(-15, 15, 2)
        size = np.array([rng.uniform(0.5, 5), rng.uniform(0.5, 2.5), 1.5])
        gap = gap_ahead((0.0, 0.0), yaw, 4.8, 2.0, pose, size)
        box = footprint_of(pose, size)
        steps = np.arange(0.0, 40.0, 0.01)
        def touches(d: float) -> bool:
            return overlap(footprint(np.array([np.cos(yaw), np.sin(yaw)]) * (d + 2.4 - 0.005), yaw, 0.01, 2.0), box)

        # the first 1 cm step at which the slid footprint touches: a 10 cm scan first (the touching
        # distances form one interval longer than the ego, 4.8 m, so it cannot be stepped over)
        coarse = next((d for d in steps[::10] if touches(d)), None)
        first = None if coarse is None else next(d for d in steps[max(0, int(round(coarse / 0.01)) - 10):] if touches(d))
        if gap is None:
            assert first is None or first > 40.0 - 4.8
        else:
            checked += 1
            assert first is not None and first == pytest.approx(max(gap, 0.0), abs=0.02)
    assert checked > 10
