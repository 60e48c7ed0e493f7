"""Rolling shutter of a spinning LiDAR: a sweep's rays split into time sectors, each
rendered from the sensor pose at its time.

A spinning LiDAR fires its rays over one revolution (~0.1 s), while the ego (and the
actors) move: each ray leaves from the sensor pose at its own firing time, and its azimuth
and elevation are in that pose's frame (docs/lidar.md). ``rasterize_lidar`` renders rays
from one pose, so a caller splits the sweep into K sectors of equal duration
(:func:`sweep_sectors`), renders each sector's rays from the sensor pose interpolated at the
sector's middle time (rotation SLERP, translation linear: :func:`omnire.interpolation.interpolate_poses`),
with the actors placed at that time (or, where the dataset's boxes hold the actors where the
sweep saw them, at the sweep's end: ``Reconstruction.sweep_actor_moment``), and puts the results back in the sweep's order with
each sector's ``index``. A ray's origin is then off by at most the sensor's motion over half
a sector (speed x duration / (2K): 2 cm at 36 km/h over a 0.1 s sweep with K = 25), its
direction by the rotation over half a sector. Rays without recorded times (a beam grid at a
pose no sensor visited) get them from their azimuth (:func:`spin_times`).
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from omnire.interpolation import interpolate_poses
from omnire.rasterization import LidarRays, RasterInputError


@dataclasses.dataclass(frozen=True)
class SweepSector:
    """Rays of one time sector of a sweep.

    Attributes:
        rays: the sector's rays, with the sensor pose at ``time``.
        index: (R_k,) int64 positions of these rays in the sweep.
        time: the sector's middle time, seconds on the log's clock.
    """

    rays: LidarRays
    index: torch.Tensor
    time: float


def spin_times(azimuth_deg: np.ndarray, start_time: float, duration: float, start_azimuth_deg: float = 0.0,
               counter_clockwise: bool = True) -> np.ndarray:
    """Firing times (R,) float64 of rays at ``azimuth_deg`` (R,) of a sensor that spins once
    in ``duration`` seconds from ``start_azimuth_deg`` at ``start_time``, counter-clockwise
    (azimuths increasing) or clockwise."""
    turn = np.asarray(azimuth_deg, dtype=np.float64) - start_azimuth_deg
    return start_time + duration * (np.remainder(turn if counter_clockwise else -turn, 360.0) / 360.0)


def sector_split(times: np.ndarray, sectors: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays fired at ``times`` (R,) seconds (R >= 1) in ``sectors`` sectors of equal duration
    between the first and the last time -> (sector of each ray (R,) int64, middle time of
    each sector (sectors,) float64)."""
    times = np.asarray(times, dtype=np.float64)
    t0, t1 = float(times.min()), float(times.max())
    span = max(t1 - t0, 1e-12)
    which = np.minimum(((times - t0) / span * sectors).astype(np.int64), sectors - 1)
    return which, t0 + (np.arange(sectors) + 0.5) * (span / sectors)


def sweep_sectors(azimuth_deg: torch.Tensor, elevation_deg: torch.Tensor, times: np.ndarray, pose_times: np.ndarray,
                  sensor_to_world: np.ndarray, min_range: float, max_range: float, sectors: int,
                  probe_range: Optional[torch.Tensor] = None) -> list[SweepSector]:
    """Split a sweep's rays (R,) (azimuths and elevations in degrees in the sensor frame at
    each ray's time, ``times`` (R,) seconds, optional ``probe_range`` (R,) metres, see
    :class:`~omnire.rasterization.LidarRays`) into ``sectors`` sectors of equal duration
    between the first and the last time; each sector holds its rays and the sensor pose
    interpolated from ``sensor_to_world`` (K, 4, 4) known at increasing ``pose_times`` (K,)
    at its middle time (held outside them). Empty sectors are left out; every ray is in
    exactly one sector."""
    times = np.asarray(times, dtype=np.float64)
    R = azimuth_deg.shape[0]
    if azimuth_deg.shape != (R,) or elevation_deg.shape != (R,) or times.shape != (R,):
        raise RasterInputError(f"azimuth_deg {tuple(azimuth_deg.shape)}, elevation_deg "
                               f"{tuple(elevation_deg.shape)}, times {times.shape}: expected three (R,) arrays")
    if probe_range is not None and probe_range.shape != (R,):
        raise RasterInputError(f"probe_range {tuple(probe_range.shape)}: expected ({R},) like azimuth_deg")
    if not np.isfinite(times).all():
        raise RasterInputError("times: non-finite values")
    if sectors < 1:
        raise RasterInputError(f"sectors: {sectors}, expected >= 1")
    if R == 0:
        return []
    which, middles = sector_split(times, sectors)
    poses = interpolate_poses(pose_times, sensor_to_world, middles)  # (sectors, 4, 4)
    dtype = azimuth_deg.dtype
    out = []
    for k in range(sectors):
        index = torch.from_numpy(np.flatnonzero(which == k)).to(azimuth_deg.device)
        if index.numel() == 0:
            continue
        pose = torch.as_tensor(poses[k], dtype=dtype if dtype.is_floating_point else torch.float64,
                               device=azimuth_deg.device)
        probe = None if probe_range is None else probe_range[index]
        out.append(SweepSector(LidarRays(pose, azimuth_deg[index], elevation_deg[index], min_range, max_range, probe),
                               index, float(middles[k])))
    return out
