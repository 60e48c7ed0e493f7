"""A rendered sweep as a point cloud, written as PLY and npz (``omnire render --lidar``,
``omnire sim`` with LiDAR).

A ray gives a point when it returns: rendered ray-drop probability below 0.5. The point lies
at the ray's expected range (the range the LiDAR loss trains: on the synthetic test scene a
pose off the recorded path gets a median error of 6 cm with it where the median range, the
range of the single Gaussian where the transmittance falls to 0.5, is off by 22 cm; docs/lidar.md)
from the sensor pose the ray was rendered from (its time sector's, omnire/lidarsweep.py).

Fields per point: ``x y z`` (float32, world metres), ``intensity`` (float32, [0, 1]),
``time`` (float64, seconds on the log's clock), ``beam`` (int16, -1 where unknown).
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch

from omnire.io.atomic import atomic_write_bytes
from omnire.lidarmodel import LidarRender
from omnire.lidarsweep import SensorPath, SweepRays, sectors_of

POINT_FIELDS = (("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"), ("time", "f8"), ("beam", "i2"))
"""Point-cloud fields and their numpy types, in file order."""


def sweep_points(render: LidarRender, sweep: SweepRays, path: SensorPath, sectors: int) -> np.ndarray:
    """The returning rays of ``render`` (rendered by ``Reconstruction.render_sweep(sweep,
    path, sectors)``) as a structured (P,) array of :data:`POINT_FIELDS`."""
    pose = np.zeros((len(sweep), 4, 4))
    for sector in sectors_of(sweep, path, sectors, dtype=torch.float64):
        pose[sector.index.numpy()] = sector.rays.sensor_to_world.numpy()
    drop = render.ray_drop.detach().cpu().numpy()
    keep = drop < 0.5
    rng = render.range.detach().cpu().numpy().astype(np.float64)[keep]
    local = sweep.local_directions[keep] * rng[:, None]
    world = np.einsum("nij,nj->ni", pose[keep, :3, :3], local) + pose[keep, :3, 3]
    out = np.zeros(int(keep.sum()), dtype=list(POINT_FIELDS))
    out["x"], out["y"], out["z"] = world[:, 0], world[:, 1], world[:, 2]
    out["intensity"] = render.intensity.detach().cpu().numpy()[keep]
    out["time"] = sweep.times[keep]
    out["beam"] = sweep.beam[keep]
    return out


def write_point_cloud(stem: Path, points: np.ndarray, comment: str = "") -> list[Path]:
    """``points`` (structured, :data:`POINT_FIELDS`) as ``<stem>.ply`` (binary little-endian,
    one ``vertex`` element) and ``<stem>.npz`` (one array per field), each written
    atomically. Returns the two paths."""
    from plyfile import PlyData, PlyElement

    stem = Path(stem)
    ply, npz = stem.with_name(stem.name + ".ply"), stem.with_name(stem.name + ".npz")
    buf = io.BytesIO()
    PlyData([PlyElement.describe(points, "vertex")], comments=[comment] if comment else []).write(buf)
    atomic_write_bytes(ply, buf.getvalue())
    buf = io.BytesIO()
    np.savez(buf, **{name: points[name] for name, _ in POINT_FIELDS})
    atomic_write_bytes(npz, buf.getvalue())
    return [ply, npz]
