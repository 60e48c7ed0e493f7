"""The Velodyne HDL-64E of KITTI's car: its datasheet facts, and its beams measured from the
sweeps, since KITTI's files hold no laser index and KITTI publishes no per-laser calibration.

Facts used (docs/lidar.md, "KITTI"):

- 64 lasers in an upper and a lower block of 32 (:data:`LASERS`), about +2 to -24.9 degrees
  of elevation (~0.4 degrees apart, unevenly: each unit has its own calibration); usable
  returns up to 120 m (:data:`MAX_RANGE_M`). KITTI spins it at 10 Hz.
- A KITTI scan is one revolution in the Velodyne frame (x forward, y left, z up), the
  returns only (rays that came back empty are not stored), without per-point time, stored
  laser by laser (the top laser first), each laser's returns in increasing azimuth from
  behind the car: the "scan unfolding" of Triess et al., IV 2020. A real scan of the
  object benchmark, cropped to the camera's view, gives 47 such scan lines (the lower
  lasers leave the crop), their median elevations falling from +2.9 to -14.6 degrees.
- Each laser sits centimetres off the optical centre (that scan's lines fit
  ``z = d tan(elevation) + offset`` with offsets of 0.11-0.21 m in the upper block), so the
  apparent elevation of a return at horizontal distance d is off by about offset / d: a
  degree at 8 m, more than the ~0.4 degrees between lasers. Elevations alone cannot tell
  the lasers apart on real scans (docs/lidar.md, "KITTI"); the file order can.

:func:`measure_beams` gives each return its scan line (:func:`scan_lines`, counted before
any thinning) when every sweep's file order gives 64 of them, each line's elevation the
median apparent elevation of its returns beyond :data:`MIN_RANGE_M`. Otherwise (a scan
written in another order) it falls back to the elevations: ``omnire.api.fit_beams`` finds
the 64 beams from the returns beyond :data:`MIN_RANGE_M` and trusts them when at least
:data:`MIN_SHARE` of those returns lie within :data:`TOLERANCE_DEG` of their beam's
elevation (sensors whose lasers sit at the optical centre, as the synthetic ones do).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from omnire.api import (BeamFit, BeamModel, estimate_azimuth_resolution, fit_beams, median_per_beam, spherical,
                        spread_sample, whole_revolution_step)

LASERS = 64
"""Lasers of the HDL-64E (upper and lower block of 32)."""
MAX_RANGE_M = 120.0
"""The datasheet's range for usable returns (metres)."""
MIN_RANGE_M = 3.0
"""Returns nearer than this are left out of the elevation measurement and its check (the
lowest laser, about -24.9 degrees, meets flat ground 1.73 m below KITTI's Velodyne at about
4.1 m, so every laser keeps its ground returns)."""
TOLERANCE_DEG = 0.08
"""A return is on its beam when its elevation lies this close to the beam's (a fifth of the
~0.4 degree spacing)."""
MIN_SHARE = 0.9
"""Share of the returns beyond :data:`MIN_RANGE_M` that must be on their beam."""
NAME = "HDL-64E (elevations measured from the sweeps)"
LINE_BREAK_DEG = 10.0
"""A return whose azimuth lies more than this below the previous return's starts the next
laser's scan line (within a line the azimuth only grows, by ~0.17 degrees a firing)."""
MIN_LINE_RETURNS = 20
"""Returns beyond :data:`MIN_RANGE_M` a scan line needs over the measured sweeps for its
elevation to be measured."""
SAMPLE_SWEEPS = 10
"""Sweeps, spread over the loaded ones, on which elevations and the azimuth step are measured."""


def scan_lines(points_velodyne: np.ndarray) -> np.ndarray:
    """(N, 3) returns of one scan in file order (Velodyne frame) -> (N,) int64 scan line of
    each, 0 for the first laser stored: a line ends where the azimuth falls back by more than
    :data:`LINE_BREAK_DEG`."""
    p = np.asarray(points_velodyne, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"scan_lines: points {p.shape}, expected (N, 3)")
    azimuth = np.rad2deg(np.arctan2(p[:, 1], p[:, 0]))
    starts = np.zeros(len(p), dtype=np.int64)
    starts[1:] = np.diff(azimuth) < -LINE_BREAK_DEG
    return np.cumsum(starts)


def measure_beams(points: list[Optional[np.ndarray]], sensor_to_world: np.ndarray,
                  lines: Optional[list[Optional[np.ndarray]]] = None) -> BeamFit:
    """The HDL-64E's beams from KITTI sweeps.

    Args:
        points: per frame, (N_i, 3) world returns or None (a missing scan).
        sensor_to_world: (F, 4, 4) Velodyne pose of each frame (NaN where no scan).
        lines: per frame, (N_i,) :func:`scan_lines` of the returns (None: elevations only).
    Returns the fit (``model`` None and ``reason`` set when it is not trusted).
    """
    local = []
    for p, M in zip(points, sensor_to_world):
        if p is None:
            local.append(None)
            continue
        local.append((np.asarray(p, dtype=np.float64) - M[:3, 3]) @ M[:3, :3])  # R^T (p - t): Velodyne frame
    why_not_lines = "no scan lines given"
    if lines is not None:
        fit = _beams_from_scan_lines(local, lines)
        if fit.model is not None:
            return fit
        why_not_lines = fit.reason
    fit = fit_beams(local, LASERS, MAX_RANGE_M, NAME, min_range=MIN_RANGE_M, tolerance_deg=TOLERANCE_DEG,
                    min_share=MIN_SHARE, sample_sweeps=SAMPLE_SWEEPS)
    if fit.model is None:
        fit.reason = f"file order: {why_not_lines}; elevations: {fit.reason}"
    return fit


def _beams_from_scan_lines(local: list[Optional[np.ndarray]], lines: list[Optional[np.ndarray]]) -> BeamFit:
    """Beam = scan line, when every sweep's file order gives :data:`LASERS` lines."""
    present = [i for i, p in enumerate(local) if p is not None and len(p)]
    if not present:
        return BeamFit(None, None, float("nan"), "no returns")
    for i in present:
        if lines[i] is None or np.shape(lines[i]) != (len(local[i]),):
            raise ValueError(f"measure_beams: sweep {i} has {len(local[i])} returns and scan lines of shape "
                             f"{np.shape(lines[i])}; expected ({len(local[i])},)")
        found = int(lines[i][-1]) + 1
        if found != LASERS:
            return BeamFit(None, None, float("nan"), f"loaded sweep {i} holds {found} scan lines, expected {LASERS}")
    sample = spread_sample(present, SAMPLE_SWEEPS)
    sph = {i: spherical(local[i]) for i in sample}
    far = {i: rng > MIN_RANGE_M for i, (rng, _, _) in sph.items()}
    line_of = np.concatenate([lines[i][far[i]] for i in sample])
    elevation_of = np.concatenate([sph[i][2][far[i]] for i in sample])
    elevations, counts = median_per_beam(elevation_of, line_of, LASERS)
    weakest = int(counts.argmin())
    if counts[weakest] < MIN_LINE_RETURNS:
        return BeamFit(None, None, float("nan"), f"scan line {weakest} has {counts[weakest]} returns beyond "
                                                  f"{MIN_RANGE_M:g} m in {len(sample)} sweeps, fewer than "
                                                  f"{MIN_LINE_RETURNS}")
    if len(np.unique(elevations)) != LASERS:
        return BeamFit(None, None, float("nan"), "two scan lines have the same median elevation")
    share = float(np.mean(np.abs(elevation_of - elevations[line_of]) <= TOLERANCE_DEG))
    steps = [estimate_azimuth_resolution(sph[i][1], lines[i]) for i in sample]
    model = BeamModel(elevations, whole_revolution_step(float(np.median(steps))), MAX_RANGE_M,
                      name="HDL-64E (scan lines in file order, elevations measured)")
    return BeamFit(model, [None if p is None else np.asarray(lines[i], dtype=np.int16) for i, p in enumerate(local)],
                   share, "")
