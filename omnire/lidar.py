"""LiDAR projected into camera views (sparse depth targets), cached per view."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from omnire.data.scene import SceneData, View


def project_points(points: np.ndarray, cam_to_world: np.ndarray, K: np.ndarray, width: int, height: int,
                   min_depth: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) world points -> (flat pixel index (P,), depth (P,)) of those in the image.
    When several points share a pixel the nearest is kept."""
    w2c = np.linalg.inv(cam_to_world)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    front = z > min_depth
    p, z = p[front], z[front]
    u = np.floor(K[0, 0] * p[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.floor(K[1, 1] * p[:, 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    idx, z = v[inside] * width + u[inside], z[inside]
    order = np.lexsort((z, idx))
    idx, z = idx[order], z[order]
    first = np.ones(len(idx), dtype=bool)
    first[1:] = idx[1:] != idx[:-1]
    return idx[first], z[first]


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
