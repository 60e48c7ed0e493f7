"""Masks of the recording vehicle itself in its cameras, estimated from the images alone.

The ego car's body (a trunk, a hood, mirrors) stays fixed in the image while the world moves
past, and its silhouette is an edge that is present in every frame. The estimate, per
camera, over the frames where the ego moves:

1. ``persistent``: the temporal median of each frame's gradient magnitude: high only on
   edges that stay put (the body's outline; the world's edges move and average out);
2. regions separated by persistent edges; the candidates touch the bottom border of the
   image (or the lower half of a side border: mirrors) and not the top border;
3. a candidate is the ego car when it is static: the median over its pixels of the
   temporal median absolute deviation of the colour is small, and its fine texture does not
   move (road asphalt passing under a side camera is uniform enough to look static in
   colour, but its grain changes from frame to frame); with LiDAR, a candidate the LiDAR
   sees into (returns projected onto it) is world, not car;
4. the accepted regions, grown over their outline (2 px) and closed, holes filled.

Pixels of the mask are left out of the losses (so of the densification statistics, which
come from the loss gradients) and of every metric. Limits: a camera whose view of the car
has no persistent outline (a body part filling the whole image) yields no mask; a static
world (ego standing still) gives no evidence, so only frames where the ego moves are used.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import ndimage

MIN_MOVE = 0.05
"""Metres the ego must move between frames for the frame to count as evidence."""
EDGE_THRESHOLD = 0.15
"""Persistent edge strength (Sobel of [0, 1] grey values after a 1-pixel blur)."""
STATIC_THRESHOLD = 0.02
"""Largest median temporal deviation (colour, [0, 1]) of a region that is the ego car."""
MIN_AREA = 0.005
"""Smallest accepted region, as a fraction of the image."""
TEXTURE_MOTION = 0.85
"""Largest ratio of the temporal deviation of the fine texture to its magnitude (both
summed over the region) of a region that is the ego car; moving texture is near 1."""
LIDAR_SEEN = 0.1
"""Largest fraction of a region's pixels near a projected LiDAR return for the ego car."""


def moving_frames(ego_poses: Optional[np.ndarray], num_frames: int) -> np.ndarray:
    """Frame indices where the ego moved more than :data:`MIN_MOVE` since the previous
    frame (all frames when the poses are unknown or the ego never moves)."""
    if ego_poses is None:
        return np.arange(num_frames)
    step = np.linalg.norm(np.diff(ego_poses[:, :3, 3], axis=0), axis=1)
    frames = np.flatnonzero(step > MIN_MOVE) + 1
    return frames if len(frames) >= 3 else np.arange(num_frames)


def estimate_ego_mask(images: np.ndarray, lidar_hits: Optional[np.ndarray] = None) -> np.ndarray:
    """(H, W) bool mask of the recording vehicle from ``images`` (T, H, W, 3) in [0, 1] of
    one camera taken while the vehicle moves (T >= 3), and optionally ``lidar_hits`` (H, W)
    bool: pixels onto which LiDAR returns of those frames project. See the module docstring."""
    if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] < 3:
        raise ValueError(f"estimate_ego_mask: expected (T >= 3, H, W, 3) images, got {images.shape}")
    T, H, W, _ = images.shape
    grey = images.mean(-1)
    grads = np.stack([np.hypot(ndimage.sobel(g, 0), ndimage.sobel(g, 1))
                      for g in (ndimage.gaussian_filter(f, 1.0) for f in grey)])
    persistent = np.median(grads, axis=0) > EDGE_THRESHOLD  # (H, W)
    median = np.median(images, axis=0)
    deviation = np.median(np.abs(images - median).max(-1), axis=0)  # (H, W)
    fine = np.stack([g - ndimage.gaussian_filter(g, 2.0) for g in grey])  # (T, H, W) fine texture
    texture_change = np.median(np.abs(fine - np.median(fine, axis=0)), axis=0)
    texture = np.median(np.abs(fine), axis=0)
    seen = None
    if lidar_hits is not None:
        seen = ndimage.binary_dilation(lidar_hits, iterations=max(1, H // 100))
    regions, n = ndimage.label(~ndimage.binary_dilation(persistent))
    mask = np.zeros((H, W), bool)
    lower = slice(H // 2, H)
    for label in range(1, n + 1):
        region = regions == label
        touches_bottom = region[-1].any() or region[lower, 0].any() or region[lower, -1].any()
        if not touches_bottom or region[0].any() or region.mean() < MIN_AREA:
            continue
        if np.median(deviation[region]) >= STATIC_THRESHOLD:
            continue
        if texture_change[region].sum() > TEXTURE_MOTION * texture[region].sum():
            continue
        if seen is not None and seen[region].mean() > LIDAR_SEEN:
            continue
        mask |= region
    if not mask.any():
        return mask
    # Take in the outline (the persistent edge between the body and the world, ~2 px wide)
    # and any parts split off by inner edges; padded so the image border is not eroded.
    padded = np.pad(mask, 4, mode="edge")
    padded = ndimage.binary_closing(ndimage.binary_dilation(padded, iterations=2), iterations=2)
    return ndimage.binary_fill_holes(padded)[4:-4, 4:-4]


def estimate_scene_ego_masks(scene, images, max_frames: int = 40) -> dict[str, np.ndarray]:
    """Estimated ego masks (H, W) bool of every camera of ``scene`` at its loaded size, from
    up to ``max_frames`` evenly spaced moving frames (``images``: an ImageCache), with the
    scene's LiDAR as a veto when it has some."""
    from omnire.lidar import project_points

    frames = moving_frames(scene.ego_poses, scene.num_frames)
    if len(frames) > max_frames:
        frames = frames[np.linspace(0, len(frames) - 1, max_frames).round().astype(int)]
    out = {}
    for cam in scene.cameras:
        stack = np.stack([images.camera_image(cam, int(f)).numpy() for f in frames])
        hits = None
        if scene.lidar is not None:
            hits = np.zeros(cam.height * cam.width, bool)
            for f in frames:
                if scene.lidar.points[int(f)] is not None:
                    idx, _ = project_points(scene.lidar.points[int(f)], cam.cam_to_world[int(f)], cam.intrinsics,
                                            cam.width, cam.height, min_depth=0.3)
                    hits[idx] = True
            hits = hits.reshape(cam.height, cam.width)
        out[cam.name] = estimate_ego_mask(stack, hits)
    return out
