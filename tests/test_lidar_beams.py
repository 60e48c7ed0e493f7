"""The LiDAR data model (LidarSweeps per-point fields, BeamModel) and omnire.beams, checked
on sweeps made from a known beam model (so every recovered quantity has an exact answer)."""
from __future__ import annotations

import numpy as np
import pytest

from omnire.beams import (assign_beams, estimate_azimuth_resolution, estimate_elevations, fit_beams, median_per_beam,
                          points_in_sensor_frame, range_image, spherical)
from omnire.data.scene import BeamModel, LidarSweeps, SceneDataError
from omnire.interpolation import interpolate_poses

MODEL = BeamModel(np.array([10.0, 3.0, 1.0, 0.5, 0.0, -0.5, -2.0, -8.0, -15.0]), 0.5, 100.0, 0.3, "toy")
OFFSETS = np.linspace(-0.24, 0.24, 9)[[4, 0, 8, 2, 6, 1, 7, 3, 5]]
"""Per-laser azimuth offsets (degrees, within half a step) of the toy sensor's beams."""


def _sweep(rng: np.random.Generator, drop: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every ray of MODEL with the beams' azimuth OFFSETS, random ranges, a fraction dropped.
    Returns sensor-frame points (N, 3), true beam (N,), true column (N,), kept mask (B*A,)."""
    d, beam, col = MODEL.directions()
    az = np.deg2rad(col * MODEL.azimuth_resolution_deg + OFFSETS[beam])
    el = np.deg2rad(MODEL.elevations_deg[beam])
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    kept = rng.random(len(d)) >= drop
    r = rng.uniform(1.0, 80.0, len(d))
    return (d * r[:, None])[kept], beam[kept], col[kept], kept


def test_beam_model_rays_and_validation():
    d, beam, col = MODEL.directions()
    assert d.shape == (9 * 720, 3) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    _, _, el = spherical(d)
    np.testing.assert_allclose(el, MODEL.elevations_deg[beam], atol=1e-9)
    assert list(MODEL.order()) == list(range(9))
    for bad, field in [(dict(elevations_deg=np.array([1.0, np.nan])), "elevations_deg"),
                       (dict(elevations_deg=np.array([1.0, 1.0])), "elevations_deg"),
                       (dict(azimuth_resolution_deg=0.0), "azimuth_resolution_deg"),
                       (dict(max_range=0.1, min_range=0.3), "max_range")]:
        kw = dict(elevations_deg=np.array([1.0, 2.0]), azimuth_resolution_deg=0.2, max_range=100.0, min_range=0.0)
        kw.update(bad)
        with pytest.raises(SceneDataError, match=field):
            BeamModel(**kw)


def test_sweeps_per_point_fields_validated():
    pts = [np.zeros((4, 3), np.float32), None]
    origins = np.array([[0.0, 0, 0], [np.nan] * 3])
    LidarSweeps(pts, origins)  # the old two-field form still works
    ok = dict(intensity=[np.ones(4, np.float32), None], times=[np.zeros(4), None],
              beams=[np.array([0, 1, -1, 8], np.int16), None], beam_model=MODEL,
              sensor_to_world=np.stack([np.eye(4), np.full((4, 4), np.nan)]))
    sweeps = LidarSweeps(pts, origins, **ok)
    assert sweeps.available_frames() == [0]
    cases = [
        ("intensity", [np.ones(3, np.float32), None], r"lidar.intensity\[0\]: shape \(3,\)"),
        ("intensity", [np.full(4, -1.0, np.float32), None], "negative"),
        ("times", [np.array([0, 0, np.nan, 0]), None], r"lidar.times\[0\]: contains NaN"),
        ("times", [np.zeros(4), np.zeros(0)], r"lidar.times\[1\]: given where lidar.points\[1\] is None"),
        ("beams", [np.array([0, 1, 2, 9], np.int16), None], r"lidar.beams\[0\]: values 0..9, expected -1..8"),
        ("beam_model", None, "without lidar.beam_model"),
        ("sensor_to_world", np.stack([np.eye(4)] * 2)[:1], "lidar.sensor_to_world: shape"),
    ]
    for field, value, message in cases:
        with pytest.raises(SceneDataError, match=message):
            LidarSweeps(pts, origins, **{**ok, field: value})
    moved = np.stack([np.eye(4), np.eye(4)])
    moved[0, 0, 3] = 1.0
    with pytest.raises(SceneDataError, match="differ from lidar.origins"):
        LidarSweeps(pts, origins, **{**ok, "sensor_to_world": moved})


def test_beams_elevations_and_azimuth_step_recovered():
    rng = np.random.default_rng(0)
    p, beam, _, _ = _sweep(rng)
    noisy = p + rng.normal(scale=0.002, size=p.shape)  # 2 mm: ~0.001 degrees at 80 m, 0.1 at 1 m
    r, az, el = spherical(noisy)
    assert (assign_beams(el, MODEL) == beam).mean() > 0.995
    est = estimate_elevations(el, MODEL.num_beams)
    np.testing.assert_allclose(est, np.sort(MODEL.elevations_deg)[::-1], atol=0.01)
    assert estimate_azimuth_resolution(az, beam) == pytest.approx(MODEL.azimuth_resolution_deg, abs=0.01)
    with pytest.raises(SceneDataError, match="found 1 elevation peaks, expected 2"):
        estimate_elevations(np.full(100, 3.0), 2)


def test_median_per_beam_equals_a_loop_of_medians():
    """Per-beam medians and counts against np.median beam by beam: even and odd counts, a
    beam without returns (NaN), returns of another sensor (-1) and past the beams left out;
    on a sweep, each laser's median elevation is its model elevation."""
    rng = np.random.default_rng(3)
    beams = rng.integers(-1, 8, 500)
    beams[beams == 4] = 9  # beam 4 has no return; 9 is past num_beams
    values = rng.normal(size=500)
    medians, counts = median_per_beam(values, beams, 6)
    for b in range(6):
        mine = values[beams == b]
        assert counts[b] == len(mine)
        assert (np.isnan(medians[b]) and not len(mine)) or medians[b] == np.median(mine)
    assert counts.sum() == ((beams >= 0) & (beams < 6)).sum() and counts[4] == 0
    p, beam, _, _ = _sweep(rng)
    measured, _ = median_per_beam(spherical(p)[2], beam, MODEL.num_beams)
    np.testing.assert_allclose(measured, MODEL.elevations_deg, atol=1e-9)
    with pytest.raises(SceneDataError, match="expected two"):
        median_per_beam(values, beams[:3], 6)


def test_fit_beams_measures_a_sensor_without_laser_indices():
    rng = np.random.default_rng(4)
    sweeps = [_sweep(rng) for _ in range(3)]
    fit = fit_beams([p for p, *_ in sweeps] + [None], MODEL.num_beams, 100.0, "toy", min_range=2.0)
    assert fit.reason == "" and fit.share_within == 1.0 and fit.beams[-1] is None
    np.testing.assert_allclose(fit.model.elevations_deg, np.sort(MODEL.elevations_deg)[::-1], atol=1e-9)
    assert fit.model.azimuth_resolution_deg == pytest.approx(MODEL.azimuth_resolution_deg, abs=1e-9)
    for (_, beam, _, _), measured in zip(sweeps, fit.beams):  # same elevation, whatever the numbering
        np.testing.assert_allclose(fit.model.elevations_deg[measured], MODEL.elevations_deg[beam], atol=1e-9)
    # Refused: elevations spread evenly (no lasers), a laser short, no returns at all.
    d = rng.normal(size=(20000, 3))
    spread = fit_beams([d / np.linalg.norm(d, axis=1, keepdims=True) * 30.0], MODEL.num_beams, 100.0, "toy")
    assert spread.model is None and spread.beams is None and spread.reason
    short = fit_beams([p for p, *_ in sweeps], MODEL.num_beams + 1, 100.0, "toy", min_range=2.0)
    assert short.model is None and "found 9 elevation peaks, expected 10" in short.reason
    assert fit_beams([None, np.zeros((0, 3))], 4, 100.0, "toy").reason == "no returns"


def test_range_image_recovers_missing_returns_exactly():
    rng = np.random.default_rng(1)
    p, beam, col, kept = _sweep(rng, drop=0.3)
    r, az, el = spherical(p)
    ri = range_image(r, az, beam, MODEL)
    assert ri.collisions == 0
    # Columns are defined up to each beam's offset: compare cell occupancy per beam row as a set.
    # Brute force: each return in the cell of its own ray (the offsets lie in (-step/2, step/2)).
    expect = np.full((MODEL.num_beams, MODEL.num_azimuths), np.nan, np.float32)
    expect[beam, col] = r
    np.testing.assert_array_equal(ri.returned, kept.reshape(MODEL.num_beams, MODEL.num_azimuths))
    np.testing.assert_allclose(ri.range, expect, rtol=1e-6)
    np.testing.assert_allclose(ri.azimuth_offset_deg, OFFSETS, atol=1e-9)
    assert (ri.point[ri.returned] >= 0).all() and (ri.point[~ri.returned] == -1).all()
    np.testing.assert_allclose(r[ri.point[ri.returned]], ri.range[ri.returned], rtol=1e-6)
    # Two returns in one cell: one collision, the nearer kept.
    twice = range_image(np.r_[r[:1], r[:1] + 5], np.r_[az[:1], az[:1]], np.r_[beam[:1], beam[:1]], MODEL)
    assert twice.collisions == 1 and np.nanmin(twice.range) == pytest.approx(r[0], rel=1e-6)


def test_points_in_sensor_frame_undoes_motion():
    # Sensor drives along +x at 10 m/s and yaws 0.1 rad/s; a point measured at time t at
    # sensor-frame position q lies at pose(t) @ q in the world.
    times = np.array([0.0, 0.1, 0.2])
    poses = np.tile(np.eye(4), (3, 1, 1))
    for k, t in enumerate(times):
        c, s = np.cos(0.1 * t), np.sin(0.1 * t)
        poses[k, :3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        poses[k, :3, 3] = [10 * t, 0, 1.8]
    rng = np.random.default_rng(2)
    q = rng.normal(size=(50, 3)) * 10
    t = rng.uniform(0, 0.2, 50)
    at = interpolate_poses(times, poses, t)
    world = np.einsum("nij,nj->ni", at[:, :3, :3], q) + at[:, :3, 3]
    np.testing.assert_allclose(points_in_sensor_frame(world, t, times, poses), q, atol=1e-9)
