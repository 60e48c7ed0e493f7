"""The two stacked Velodyne VLP-32C of Argoverse 2's cars: the beam model of the upper one
(``up_lidar``, the pose of every sweep) and the beam of each return.

Facts used (docs/lidar.md, "Argoverse 2"):

- Elevations: the 32 vertical angles of the VLP-32C user manual (-25 to +15 degrees,
  :data:`DATASHEET_ELEVATIONS_DEG`); azimuth step 0.2 degrees at 10 Hz, range up to 200 m.
- A sweep file holds both sensors' returns, ``laser_number`` 0-31 from ``up_lidar`` and
  32-63 from ``down_lidar`` (mounted upside down and tilted, 11 cm lower). AV2 does not say
  which laser number has which elevation: :func:`laser_elevations` measures it from the
  returns in ``up_lidar``'s frame and matches it to the datasheet (on the av2-api fixture
  log every laser's median elevation is a datasheet angle to 0.03 degrees).

The sweep's pose is ``up_lidar``'s, so its 32 lasers are the beams; ``down_lidar``'s
returns are "another sensor" (beam -1): they supervise depth but not the ray-drop model,
and a rendered sweep is ``up_lidar``'s.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from omnire.api import BeamModel, median_per_beam, points_in_sensor_frame, spherical

DATASHEET_ELEVATIONS_DEG = np.array([
    -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667, -2.333,
    -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0,
    10.333, 15.0,
])
"""(32,) the VLP-32C's vertical angles in degrees, ascending (user manual)."""

LASERS = 32
"""Lasers per VLP-32C: ``laser_number`` 0-31 is ``up_lidar``, 32-63 ``down_lidar``."""

MATCH_DEG = 0.2
"""A laser's measured median elevation must lie this close to its datasheet angle."""

MIN_RANGE_M = 2.0
"""Returns nearer than this are left out of the elevation measurement (the lasers' own
offsets from the optical centre bend near returns' elevations)."""


def laser_elevations(points: np.ndarray, times: np.ndarray, lasers: np.ndarray, pose_times: np.ndarray,
                     sensor_to_world: np.ndarray) -> Optional[np.ndarray]:
    """(32,) datasheet elevation of each ``up_lidar`` laser number, or None when the returns
    do not show the VLP-32C's 32 angles (a sweep written without laser numbers).

    Args:
        points: (N, 3) world returns; times: (N,) their times; lasers: (N,) ``laser_number``.
        pose_times, sensor_to_world: ``up_lidar``'s track, (K,) seconds and (K, 4, 4).
    Each laser's median elevation in the sensor frame at its returns' own times is matched
    to the nearest datasheet angle; every laser must find its own angle within
    :data:`MATCH_DEG`.
    """
    up = (lasers < LASERS) & np.isfinite(times)
    rng, _, el = spherical(points_in_sensor_frame(points[up], times[up], pose_times, sensor_to_world))
    lasers = lasers[up]
    far = rng > MIN_RANGE_M
    measured, _ = median_per_beam(el[far], lasers[far], LASERS)
    if np.isnan(measured).any():
        return None
    nearest = np.abs(measured[:, None] - DATASHEET_ELEVATIONS_DEG[None]).argmin(axis=1)
    chosen = DATASHEET_ELEVATIONS_DEG[nearest]
    if len(set(nearest.tolist())) != LASERS or np.abs(measured - chosen).max() > MATCH_DEG:
        return None
    return chosen


def beam_model(elevations_deg: np.ndarray) -> BeamModel:
    """``up_lidar``'s :class:`BeamModel`: beam ``k`` is laser number ``k``."""
    return BeamModel(elevations_deg, azimuth_resolution_deg=0.2, max_range=200.0, name="VLP-32C (up_lidar)")


def beams_of(lasers: np.ndarray) -> np.ndarray:
    """(N,) ``laser_number`` -> (N,) int16 beam: the laser number for ``up_lidar``'s
    returns, -1 (another sensor) for ``down_lidar``'s."""
    lasers = np.asarray(lasers).astype(np.int16)
    return np.where(lasers < LASERS, lasers, -1).astype(np.int16)
