"""Point-cloud helpers: thinning LiDAR sweeps (readers), and for initialising nodes voxel
downsampling, nearest-neighbour scales, colouring from images, far-field shells,
points-in-box tests."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from scipy.spatial import cKDTree


THIN_SEED = 0
"""Seed of :func:`thin_points`, combined with the key of each sweep."""


def thin_points(points: np.ndarray, max_points: int, key: int) -> np.ndarray:
    """(N, ...) rows -> (min(N, max_points), ...) rows drawn at random without replacement,
    in their original order; ``max_points`` 0 keeps all. The draw is seeded by
    (:data:`THIN_SEED`, ``key``): a reader passes something fixed per sweep (its timestamp or
    frame number in the log), so a sweep is thinned the same way whatever frames are loaded."""
    if not 0 < max_points < len(points):
        return points
    rng = np.random.default_rng((THIN_SEED, int(key)))
    return points[np.sort(rng.choice(len(points), max_points, replace=False))]


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """(N,3) -> (M,3): the mean of the points in each occupied voxel of edge ``voxel``."""
    if len(points) == 0 or voxel <= 0:
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, points)
    return (sums / counts[:, None]).astype(points.dtype)


def knn_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """(N,3) -> (N,) mean distance to the k nearest other points (isotropic init scale)."""
    if len(points) <= 1:
        return np.full(len(points), 0.1)
    k = min(k, len(points) - 1)
    d, _ = cKDTree(points).query(points, k=k + 1)
    return np.maximum(d[:, 1:].mean(axis=1), 1e-4)


def points_in_box(points: np.ndarray, box_to_world: np.ndarray, size: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(N,3) world points, (4,4) box pose, (3,) size (l,w,h) -> (N,) bool inside."""
    local = (points - box_to_world[:3, 3]) @ box_to_world[:3, :3]
    return np.all(np.abs(local) <= size / 2 + margin, axis=1)


def colour_from_images(points: np.ndarray, scene, images, frames: np.ndarray, max_views: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Colour (N,3) world points by projecting them into training images.

    Each point takes the colour from the view where it lies closest to the camera (in
    front of it and inside the image), which favours the sharpest observation. Occlusion
    is not tested (a point hidden behind a car takes the car's colour in that view); the
    optimisation corrects such colours quickly. Returns colours in [0,1] and a (N,) mask
    of points seen at all (unseen ones are grey).
    """
    N = len(points)
    colours = np.full((N, 3), 0.5, dtype=np.float32)
    best = np.full(N, np.inf)
    views = [(c, int(f)) for f in frames for c in range(len(scene.cameras))]
    if len(views) > max_views:
        views = [views[i] for i in np.linspace(0, len(views) - 1, max_views).round().astype(int)]
    for cam_idx, frame in views:
        cam = scene.cameras[cam_idx]
        w2c = np.linalg.inv(cam.cam_to_world[frame])
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        front = z > 0.5
        uv = np.full((N, 2), -1.0)
        uv[front] = (p[front, :2] / z[front, None]) @ cam.intrinsics[:2, :2].T + cam.intrinsics[:2, 2]
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        better = inside & (z < best)
        if not better.any():
            continue
        img = images.camera_image(cam, frame).numpy()
        u = uv[better, 0].astype(int)
        v = uv[better, 1].astype(int)
        colours[better] = img[v, u]
        best[better] = z[better]
    return colours, np.isfinite(best)


def far_shell(center: np.ndarray, radius: float, count: int, rng: np.random.Generator, min_z: Optional[float] = None) -> np.ndarray:
    """(count,3) random points in a shell between 1x and 3x ``radius`` around ``center``
    (for far-field content LiDAR does not reach), above ``min_z`` when given."""
    dirs = rng.normal(size=(count, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    if min_z is not None:
        dirs[:, 2] = np.abs(dirs[:, 2])  # upper hemisphere: sky and building tops
    r = radius * (1.0 + 2.0 * rng.random(count))
    pts = center + dirs * r[:, None]
    if min_z is not None:
        pts[:, 2] = np.maximum(pts[:, 2], min_z)
    return pts


def to_tensor(a: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)
