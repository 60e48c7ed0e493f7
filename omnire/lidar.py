"""LiDAR projected into camera views (sparse depth targets), cached per view."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from omnire.data.scene import LidarSweeps, SceneData, View


def project_to_pixels(points: np.ndarray, cam_to_world: np.ndarray, K: np.ndarray, width: int, height: int,
                      min_depth: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(N,3) world points -> (column (P,), row (P,), depth (P,), index into ``points`` (P,))
    of the points in front of the camera that land in the image (every one of them)."""
    w2c = np.linalg.inv(cam_to_world)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    front = np.nonzero(z > min_depth)[0]
    p, z = p[front], z[front]
    u = np.floor(K[0, 0] * p[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.floor(K[1, 1] * p[:, 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return u[inside], v[inside], z[inside], front[inside]


def project_points(points: np.ndarray, cam_to_world: np.ndarray, K: np.ndarray, width: int, height: int,
                   min_depth: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) world points -> (flat pixel index (P,), depth (P,)) of those in the image.
    When several points share a pixel the nearest is kept."""
    u, v, z, _ = project_to_pixels(points, cam_to_world, K, width, height, min_depth)
    idx = v * width + u
    order = np.lexsort((z, idx))
    idx, z = idx[order], z[order]
    first = np.ones(len(idx), dtype=bool)
    first[1:] = idx[1:] != idx[:-1]
    return idx[first], z[first]


def near_upper_limit(sweeps: LidarSweeps, frames: list[int], margin_deg: float,
                     min_range: float = 5.0, percentile: float = 99.5) -> Optional[np.ndarray]:
    """Which returns of ``frames`` (their points concatenated in order: (N,) bool) lie within
    ``margin_deg`` of the LiDAR's upper elevation limit, seen from each frame's sensor origin.
    The limit is the ``percentile`` of the elevations of returns more than ``min_range``
    metres away horizontally (near returns, e.g. of the recording vehicle, are skewed by
    where the origin sits). None when no frame has a finite origin."""
    elevations, usable = [], []
    for f in frames:
        rel = sweeps.points[f].astype(np.float64) - sweeps.origins[f]
        horizontal = np.linalg.norm(rel[:, :2], axis=1)
        elevations.append(np.degrees(np.arctan2(rel[:, 2], horizontal)))
        usable.append(np.isfinite(horizontal) & (horizontal > min_range))
    elevation, usable = np.concatenate(elevations), np.concatenate(usable)
    if not usable.any():
        return None
    limit = np.percentile(elevation[usable], percentile)
    return np.isfinite(elevation) & (elevation >= limit - margin_deg)


class LidarDepthTargets:
    """Per-view sparse depth from the LiDAR sweep of the view's frame (None: no LiDAR)."""

    def __init__(self, scene: SceneData, device: torch.device) -> None:
        self.scene = scene
        self.device = device
        self._cache: dict[View, Optional[tuple[torch.Tensor, torch.Tensor]]] = {}

    def get(self, view: View) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
        if view in self._cache:
            return self._cache[view]
        out = None
        if self.scene.lidar is not None and self.scene.lidar.points[view.frame] is not None:
            cam = self.scene.cameras[view.camera]
            idx, z = project_points(self.scene.lidar.points[view.frame], cam.cam_to_world[view.frame],
                                    cam.intrinsics, cam.width, cam.height)
            out = (torch.from_numpy(idx).to(self.device), torch.from_numpy(z).float().to(self.device))
        self._cache[view] = out
        return out
