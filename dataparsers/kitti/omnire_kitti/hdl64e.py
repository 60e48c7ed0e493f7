"""The Velodyne HDL-64E of KITTI's car: its datasheet facts, and its beams measured from the
sweeps, since KITTI's files hold no laser index and KITTI publishes no per-laser calibration.

Facts used (docs/lidar.md, "KITTI"):

- 64 lasers in an upper and a lower block of 32 (:data:`LASERS`), about +2 to -24.9 degrees
  of elevation (~0.4 degrees apart, unevenly: each unit has its own calibration); usable
  returns up to 120 m (:data:`MAX_RANGE_M`). KITTI spins it at 10 Hz.
- A KITTI scan is one revolution in the Velodyne frame (x forward, y left, z up), the
  returns only (rays that came back empty are not stored), without per-point time.

:func:`measure_beams` reads the elevations of returns beyond :data:`MIN_RANGE_M` in that
frame (each laser sits a few centimetres off the optical centre, which bends the apparent
elevation of near returns by about offset / range), finds the 64 beams with
``omnire.api.fit_beams``, and trusts them when at least :data:`MIN_SHARE` of those returns
lie within :data:`TOLERANCE_DEG` of their beam's elevation.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from omnire.api import BeamFit, fit_beams

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


def measure_beams(points: list[Optional[np.ndarray]], sensor_to_world: np.ndarray) -> BeamFit:
    """The HDL-64E's beams from KITTI sweeps.

    Args:
        points: per frame, (N_i, 3) world returns or None (a missing scan).
        sensor_to_world: (F, 4, 4) Velodyne pose of each frame (NaN where no scan).
    Returns the fit (``model`` None and ``reason`` set when it is not trusted).
    """
    local = []
    for p, M in zip(points, sensor_to_world):
        if p is None:
            local.append(None)
            continue
        local.append((np.asarray(p, dtype=np.float64) - M[:3, 3]) @ M[:3, :3])  # R^T (p - t): Velodyne frame
    return fit_beams(local, LASERS, MAX_RANGE_M, NAME, min_range=MIN_RANGE_M, tolerance_deg=TOLERANCE_DEG,
                     min_share=MIN_SHARE)
