"""Beam geometry of a spinning LiDAR: returns in spherical sensor coordinates, the beam of
each return, beam models estimated from returns, and the range image of a sweep with its
missing returns (ray drop). Conventions in docs/lidar.md.

Sensor frame: x forward, y left, z up; azimuth counter-clockwise from +x in [0, 360)
degrees, elevation above the x-y plane in degrees.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from omnire.data.scene import BeamModel, SceneDataError
from omnire.interpolation import interpolate_poses


def points_in_sensor_frame(points: np.ndarray, times: np.ndarray, pose_times: np.ndarray,
                           sensor_to_world: np.ndarray) -> np.ndarray:
    """World points (N, 3) measured at ``times`` (N,) -> (N, 3) float64 in the sensor frame
    at each point's own time: the sensor poses (K, 4, 4) known at increasing ``pose_times``
    (K,) are interpolated (rotation SLERP, translation linear), which undoes the motion of
    the sensor during a sweep (~1 m at 36 km/h over 0.1 s)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or np.shape(times) != (len(points),):
        raise SceneDataError(f"points {points.shape} and times {np.shape(times)}: expected (N, 3) and (N,)")
    pose = interpolate_poses(pose_times, sensor_to_world, np.asarray(times, dtype=np.float64))  # (N, 4, 4)
    rel = points - pose[:, :3, 3]
    return np.einsum("nji,nj->ni", pose[:, :3, :3], rel)  # R^T (p - t)


def spherical(points_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor-frame points (N, 3) -> range (N,) metres, azimuth (N,) degrees in [0, 360),
    elevation (N,) degrees."""
    p = np.asarray(points_sensor, dtype=np.float64)
    rng = np.linalg.norm(p, axis=1)
    az = np.rad2deg(np.arctan2(p[:, 1], p[:, 0])) % 360.0
    el = np.rad2deg(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    return rng, az, el


def assign_beams(elevation_deg: np.ndarray, model: BeamModel) -> np.ndarray:
    """(N,) elevations in degrees -> (N,) int16 index of the beam with the nearest elevation."""
    order = np.argsort(model.elevations_deg)
    sorted_el = model.elevations_deg[order]
    mid = (sorted_el[1:] + sorted_el[:-1]) / 2.0  # (B-1,) decision boundaries
    return order[np.searchsorted(mid, np.asarray(elevation_deg, dtype=np.float64))].astype(np.int16)


def median_per_beam(values: np.ndarray, beams: np.ndarray, num_beams: int) -> tuple[np.ndarray, np.ndarray]:
    """The median of ``values`` (N,) over the returns of each beam, and how many returns each
    beam has: ``beams`` (N,) integer beam of each return (values outside 0..num_beams-1, e.g.
    -1 for another sensor, are left out) -> medians (num_beams,) float64 (NaN for a beam
    without returns) and counts (num_beams,) int64. With the elevations of returns in the
    sensor frame it measures each laser's elevation where the files number the lasers (a
    ring or laser column) but do not give their angles."""
    values = np.asarray(values, dtype=np.float64)
    beams = np.asarray(beams)
    if values.shape != beams.shape or values.ndim != 1:
        raise SceneDataError(f"median_per_beam: values {values.shape} and beams {beams.shape}; expected two (N,)")
    keep = (beams >= 0) & (beams < num_beams)
    b = beams[keep].astype(np.int64)
    v = values[keep]
    order = np.lexsort((v, b))  # by beam, then value
    b, v = b[order], v[order]
    counts = np.bincount(b, minlength=num_beams).astype(np.int64)
    start = np.cumsum(counts) - counts
    has = counts > 0
    medians = np.full(num_beams, np.nan)
    medians[has] = (v[(start + (counts - 1) // 2)[has]] + v[(start + counts // 2)[has]]) / 2.0
    return medians, counts


def estimate_elevations(elevation_deg: np.ndarray, num_beams: int, bin_deg: float = 0.01,
                        min_separation_deg: float = 0.08) -> np.ndarray:
    """Beam elevations (num_beams,) in degrees, top to bottom, from the elevations (N,) of
    many returns: the ``num_beams`` most populated peaks of a fine histogram (smoothed over
    3 bins, peaks at least ``min_separation_deg`` apart), each refined to the median of the
    returns nearer to it than to its neighbours. Needs the returns' elevations in the sensor
    frame at their own time (:func:`points_in_sensor_frame`), else the ego motion blurs them."""
    el = np.asarray(elevation_deg, dtype=np.float64)
    lo, hi = el.min() - 2 * bin_deg, el.max() + 2 * bin_deg
    hist, edges = np.histogram(el, bins=max(3, int(np.ceil((hi - lo) / bin_deg))), range=(lo, hi))
    smooth = np.convolve(hist, np.ones(3), mode="same")
    peak = np.flatnonzero((smooth[1:-1] >= smooth[:-2]) & (smooth[1:-1] > smooth[2:]) & (smooth[1:-1] > 0)) + 1
    centres = (edges[peak] + edges[peak + 1]) / 2.0
    chosen: list[float] = []
    for k in np.argsort(-smooth[peak], kind="stable"):  # strongest first, skipping near duplicates
        if all(abs(centres[k] - c) >= min_separation_deg for c in chosen):
            chosen.append(float(centres[k]))
        if len(chosen) == num_beams:
            break
    if len(chosen) < num_beams:
        raise SceneDataError(f"estimate_elevations: found {len(chosen)} elevation peaks, expected {num_beams}")
    est = np.sort(np.array(chosen))
    for _ in range(2):  # refine: median of the returns in each beam's cell
        mid = (est[1:] + est[:-1]) / 2.0
        cell = np.searchsorted(mid, el)
        near = np.abs(el - est[cell]) < np.minimum(min_separation_deg, bin_deg * 5)
        est = np.array([np.median(el[near & (cell == b)]) if (near & (cell == b)).any() else est[b]
                        for b in range(num_beams)])
    return est[::-1]


def estimate_azimuth_resolution(azimuth_deg: np.ndarray, beams: np.ndarray) -> float:
    """Azimuth step (degrees) between successive firings of a beam, from one sweep: the
    median gap between the sorted azimuths of each beam's returns (missing returns make a
    few gaps of two or more steps, which the median ignores)."""
    gaps = []
    for b in np.unique(beams[beams >= 0]):
        a = np.sort(azimuth_deg[beams == b])
        d = np.diff(a)
        gaps.append(d[d > 1e-6])
    gaps = np.concatenate(gaps) if gaps else np.zeros(0)
    if len(gaps) == 0:
        raise SceneDataError("estimate_azimuth_resolution: no beam has two returns")
    return float(np.median(gaps))


def spread_sample(indices: list[int], count: int) -> list[int]:
    """Up to ``count`` of ``indices`` (sweeps with returns), spread evenly from the first to
    the last, in order and without repeats."""
    return sorted({indices[int(k)] for k in np.linspace(0, len(indices) - 1, min(count, len(indices)))})


def whole_revolution_step(step_deg: float) -> float:
    """A measured azimuth step (degrees) rounded so that one revolution holds a whole number
    of steps (the width of a range image)."""
    return 360.0 / int(round(360.0 / step_deg))


@dataclasses.dataclass
class RangeImage:
    """One sweep on its beam grid (rows = beam index, columns = azimuth bins).

    Attributes:
        range: (B, A) float32 metres, NaN where the ray returned nothing.
        returned: (B, A) bool, False = a missing return (ray drop, sky, beyond max range).
        point: (B, A) int64 index of the return into the sweep's points (-1 where none).
        azimuth_offset_deg: (B,) firing azimuth of column 0 of each beam, in [-step/2,
            step/2) (the per-laser azimuth offset modulo the step, estimated from the
            sweep); column k fires at offset + k * step.
        collisions: returns that fell on an occupied cell (the nearer one in range is kept).
    """

    range: np.ndarray
    returned: np.ndarray
    point: np.ndarray
    azimuth_offset_deg: np.ndarray
    collisions: int


def range_image(ranges: np.ndarray, azimuth_deg: np.ndarray, beams: np.ndarray, model: BeamModel) -> RangeImage:
    """The (beams x azimuth bins) range image of one sweep and its "no return" mask.

    Args:
        ranges, azimuth_deg: (N,) of each return in the sensor frame at its own time.
        beams: (N,) beam index (-1 = another sensor: ignored).
        model: the sensor's :class:`BeamModel`.
    A laser fires at azimuths ``offset_b + k * step``; the offset of each beam is the
    circular mean of its returns' azimuths modulo the step, so per-laser azimuth offsets of
    the hardware do not split one firing over two bins.
    """
    ranges = np.asarray(ranges, dtype=np.float64)
    azimuth_deg = np.asarray(azimuth_deg, dtype=np.float64)
    beams = np.asarray(beams)
    n = len(ranges)
    if azimuth_deg.shape != (n,) or beams.shape != (n,):
        raise SceneDataError(f"range_image: ranges {ranges.shape}, azimuth_deg {azimuth_deg.shape}, beams "
                             f"{beams.shape}; expected three (N,) arrays")
    B, A = model.num_beams, model.num_azimuths
    step = 360.0 / A
    keep = np.flatnonzero((beams >= 0) & (beams < B))
    b = beams[keep].astype(np.int64)
    phase = 2 * np.pi * (azimuth_deg[keep] % step) / step
    s = np.bincount(b, np.sin(phase), minlength=B)
    c = np.bincount(b, np.cos(phase), minlength=B)
    offset = np.arctan2(s, c) / (2 * np.pi) * step  # (B,) in [-step/2, step/2]: column k is near k * step
    offset = np.where(offset >= step / 2, offset - step, offset)
    col = np.round((azimuth_deg[keep] - offset[b]) / step).astype(np.int64) % A
    cell = b * A + col
    order = np.lexsort((ranges[keep], cell))  # by cell, nearest first
    cell_s = cell[order]
    first = np.ones(len(cell_s), dtype=bool)
    first[1:] = cell_s[1:] != cell_s[:-1]
    point = np.full(B * A, -1, dtype=np.int64)
    point[cell_s[first]] = keep[order[first]]
    rng = np.full(B * A, np.nan, dtype=np.float32)
    hit = point >= 0
    rng[hit] = ranges[point[hit]]
    return RangeImage(rng.reshape(B, A), hit.reshape(B, A), point.reshape(B, A), offset,
                      int(len(cell_s) - first.sum()))


@dataclasses.dataclass
class BeamFit:
    """The beams of a sensor whose returns carry no laser index, measured from its sweeps
    (:func:`fit_beams`).

    Attributes:
        model: the measured :class:`BeamModel`, None when the measurement is not trusted.
        beams: per sweep, (N_i,) int16 beam of each return (None where the sweep is None,
            and everywhere when ``model`` is None).
        share_within: share of the returns beyond ``min_range`` lying within the tolerance
            of their beam's elevation (NaN when no elevations were found).
        reason: empty when trusted, else one line saying why not.
    """

    model: Optional[BeamModel]
    beams: Optional[list[Optional[np.ndarray]]]
    share_within: float
    reason: str


def fit_beams(points_sensor: list[Optional[np.ndarray]], num_beams: int, max_range: float, name: str,
              min_range: float = 3.0, tolerance_deg: float = 0.08, min_share: float = 0.9,
              min_beam_share: float = 0.05, sample_sweeps: int = 10) -> BeamFit:
    """Measure a spinning LiDAR's beams from sweeps without laser indices.

    Args:
        points_sensor: per sweep, (N_i, 3) returns in the sensor frame (None = no sweep).
            Each sweep must be one revolution seen from one pose (a motion-corrected or
            stationary sweep), since the elevations are read from these coordinates.
        num_beams: lasers of the sensor (its datasheet); max_range: metres (its datasheet).
        min_range: only returns farther than this measure the elevations and the share
            (a laser's offset from the optical centre bends near returns' elevations).
        tolerance_deg, min_share: the fit is trusted when at least ``min_share`` of those
            returns lie within ``tolerance_deg`` of their beam's elevation, and every beam
            holds at least ``min_beam_share`` of the mean count of sampled returns per beam
            (else a peak of noise stands in for a laser).
        sample_sweeps: the elevations and the azimuth step are measured on this many
            sweeps spread over the log (all sweeps get beams).
    The elevations are :func:`estimate_elevations` of the sampled returns, each return's
    beam :func:`assign_beams`, the azimuth step :func:`estimate_azimuth_resolution`
    rounded to a whole number of steps per revolution.
    """
    present = [i for i, p in enumerate(points_sensor) if p is not None and len(p)]
    if not present:
        return BeamFit(None, None, float("nan"), "no returns")
    sample = spread_sample(present, sample_sweeps)
    sph = {i: spherical(points_sensor[i]) for i in sample}
    far_el = np.concatenate([el[rng > min_range] for rng, _, el in sph.values()])
    if len(far_el) < 10 * num_beams:
        return BeamFit(None, None, float("nan"), f"{len(far_el)} returns beyond {min_range:g} m, too few to "
                                                  f"measure {num_beams} beams")
    try:
        elevations = estimate_elevations(far_el, num_beams)
    except SceneDataError as err:
        return BeamFit(None, None, float("nan"), str(err))
    probe = BeamModel(elevations, 360.0, max_range, name=name)  # the azimuth step is measured below
    counts = np.bincount(assign_beams(far_el, probe), minlength=num_beams)
    weakest = int(counts.argmin())
    if counts[weakest] < min_beam_share * len(far_el) / num_beams:  # a noise peak, not a laser
        return BeamFit(None, None, float("nan"), f"the beam at {elevations[weakest]:.2f} deg holds "
                                                  f"{counts[weakest]} of {len(far_el)} sampled returns, not one of "
                                                  f"{num_beams} lasers")
    beams: list[Optional[np.ndarray]] = [None] * len(points_sensor)
    within = total = 0
    steps = []
    for i in present:
        rng, az, el = sph[i] if i in sph else spherical(points_sensor[i])
        b = assign_beams(el, probe)
        far = rng > min_range
        within += int((np.abs(el[far] - elevations[b[far]]) <= tolerance_deg).sum())
        total += int(far.sum())
        if i in sph and len(b) > 1:
            try:
                steps.append(estimate_azimuth_resolution(az, b))
            except SceneDataError:  # no beam with two returns in this sweep
                pass
        beams[i] = b
    share = within / max(total, 1)
    if share < min_share:
        return BeamFit(None, None, share, f"only {share:.1%} of the returns beyond {min_range:g} m lie within "
                                          f"{tolerance_deg:g} deg of their beam's elevation (at least {min_share:.0%} "
                                          f"expected of {num_beams} beams)")
    if not steps:
        return BeamFit(None, None, share, "no beam has two returns in a sweep: the azimuth step is unknown")
    model = BeamModel(elevations, whole_revolution_step(float(np.median(steps))), max_range, name=name)
    return BeamFit(model, beams, share, "")
