"""The LiDARs of a nuPlan merged point cloud, and the beams of its top LiDAR.

Facts used (sources in dataparsers/nuplan/README.md, "LiDAR beams"):

- Each record of a merged cloud holds ``x y z intensity ring lidar_info`` (``.pcd``; the
  devkit's ``to_pcd_bin2`` writes these six), the returns of every LiDAR in the frame of
  the log's ``lidar`` row.
- ``lidar_info`` says which LiDAR measured the return: 0 top, 1 right A-pillar, 2 left
  A-pillar, 3 back, 4 front (the devkit's ``prepare_pointcloud_points``; a later reader of
  the released clouds, py123d, has 1 and 2 the other way round; only 0 matters here); ``ring`` is the
  laser of the return within its own LiDAR (the devkit keeps some rings 0-39 of the A-pillar
  LiDARs).
- Nothing public gives the LiDARs' models or laser angles, and the records carry no time.

So the top LiDAR (:data:`TOP`) is the sweep's sensor: its rings are the beams, the other
LiDARs' returns have beam -1 (they supervise depth, not the ray-drop model). Its beam model
is measured on :data:`ESTIMATE_SWEEPS` sweeps spread over the log in the ``lidar`` row's frame
(:func:`top_beam_model`) and trusted only when every ring holds enough returns, lies on a
narrow cone and has its own elevation; otherwise the sweeps get no beams.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from omnire.api import BeamModel, SceneDataError, estimate_azimuth_resolution, median_per_beam, spherical
from omnire_nuplan.database import NuPlanDataError

TOP = 0
"""``lidar_info`` of the top LiDAR, the sweep's sensor."""
ESTIMATE_SWEEPS = 4
"""The beam model is measured on this many loaded sweeps, spread evenly over the log (a ring
aimed at open sky can go without returns for a while); the ring count is every loaded
sweep's largest top-LiDAR ring + 1, so a ring first seen late leaves the model untrusted
(no beams, a warning) instead of failing the log."""
MIN_RANGE_M = 2.0
"""Returns nearer than this are left out of the elevation measurement (a laser's offset from
the optical centre bends near returns' elevations)."""
MIN_RING_RETURNS = 20
"""A ring needs this many returns beyond :data:`MIN_RANGE_M` for its elevation to count."""
MAX_RING_SPREAD_DEG = 0.1
"""A ring's returns must lie this close (median absolute deviation, degrees) to its median
elevation; more means the ``lidar`` row's frame is not the top LiDAR's own."""
MIN_RING_SEPARATION_DEG = 0.05
"""Two rings' elevations must differ by at least this many degrees."""
MAX_ID = 32767
"""Largest ``ring`` / ``lidar_info`` value read (they are kept as int16)."""


def ring_and_lidar(records: np.ndarray, path: Path) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """``ring`` and ``lidar_info`` of a blob's records (N,) as two (N,) int16 arrays, or None
    when the blob lacks either field. A value that is not a whole number in 0..:data:`MAX_ID`
    is a :class:`NuPlanDataError` naming the file and field."""
    names = records.dtype.names or ()
    if "ring" not in names or "lidar_info" not in names:
        return None
    out = []
    for field in ("ring", "lidar_info"):
        v = np.asarray(records[field], dtype=np.float64)
        with np.errstate(invalid="ignore"):
            bad = ~(np.isfinite(v) & (v >= 0) & (v <= MAX_ID) & (v == np.round(v)))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise NuPlanDataError(f"{path}: field {field} must hold whole numbers in 0..{MAX_ID} (found {v[i]:g} at "
                                  f"point {i}, {int(bad.sum())} of {len(v)} values; {field} numbers "
                                  f"{'a LiDAR' if field == 'lidar_info' else 'the laser within its LiDAR'})")
        out.append(v.astype(np.int16))
    return out[0], out[1]


def top_beam_model(sweeps: list[tuple[np.ndarray, np.ndarray, np.ndarray]], ring_count: int,
                   name: str) -> tuple[Optional[BeamModel], str]:
    """The top LiDAR's :class:`BeamModel` measured from sweeps, or None and why it is not
    trusted.

    Args:
        sweeps: per sweep (xyz (N, 3) in the ``lidar`` row's frame, ring (N,), lidar_info
            (N,)), every record of the blob (not thinned: the azimuth step needs them all).
        ring_count: the top LiDAR's rings (the largest ring of every loaded sweep + 1).
        name: the model's name.
    Beam ``r`` is ring ``r``; its elevation is the median of ring ``r``'s returns beyond
    :data:`MIN_RANGE_M`, measured on ``sweeps``. The azimuth step is
    :func:`estimate_azimuth_resolution` on the first sweep, the maximum range the farthest
    return rounded up to a metre (no datasheet gives it).
    """
    top = [(xyz[lid == TOP], ring[lid == TOP]) for xyz, ring, lid in sweeps]
    where = f"{len(sweeps)} sweep(s) spread over the log"
    if not sum(len(r) for _, r in top):
        return None, f"no return of the top LiDAR (lidar_info {TOP}) in {where}"
    rings = np.concatenate([r for _, r in top]).astype(np.int64)
    rng, _, el = spherical(np.concatenate([p for p, _ in top]))
    B = int(ring_count)
    far = rng > MIN_RANGE_M
    elevations, counts = median_per_beam(el[far], rings[far], B)
    few = np.flatnonzero(counts < MIN_RING_RETURNS)
    if len(few):
        return None, (f"{len(few)} of the top LiDAR's {B} rings (ring {few[0]}: {counts[few[0]]} returns) have fewer "
                      f"than {MIN_RING_RETURNS} returns beyond {MIN_RANGE_M:g} m in {where}")
    spread, _ = median_per_beam(np.abs(el[far] - elevations[rings[far]]), rings[far], B)
    worst = int(np.argmax(spread))
    if spread[worst] > MAX_RING_SPREAD_DEG:
        return None, (f"ring {worst}'s returns lie {spread[worst]:.2f} degrees (median) from its median elevation, more "
                      f"than {MAX_RING_SPREAD_DEG} (the lidar row's frame is not the top LiDAR's own)")
    order = np.argsort(elevations)
    gaps = np.diff(elevations[order])
    if B > 1 and gaps.min() < MIN_RING_SEPARATION_DEG:
        k = int(np.argmin(gaps))
        return None, (f"rings {order[k]} and {order[k + 1]} have elevations {gaps[k]:.3f} degrees apart, less than "
                      f"{MIN_RING_SEPARATION_DEG} (not distinct beams)")
    (p0, r0) = top[0]
    try:
        step = estimate_azimuth_resolution(spherical(p0)[1], r0)
        model = BeamModel(elevations, step, float(np.ceil(rng.max())), name=name)
    except SceneDataError as e:
        return None, str(e)
    return model, ""


def beams_of(ring: np.ndarray, lidar: np.ndarray) -> np.ndarray:
    """(N,) int16 beam of each return: its ring for the top LiDAR, -1 for the others."""
    return np.where(lidar == TOP, ring, -1).astype(np.int16)


def top_ring_count(ring: np.ndarray, lidar: np.ndarray) -> int:
    """Largest top-LiDAR ring of a blob + 1 (0 without top-LiDAR returns)."""
    top = ring[lidar == TOP]
    return int(top.max()) + 1 if len(top) else 0
