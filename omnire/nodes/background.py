"""Background node: static Gaussians in the world frame.

Initialised from the LiDAR of the training frames (points inside the boxes of actors that
other nodes model are removed), voxel-downsampled, coloured from the images, plus random
far points for what LiDAR does not reach.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from omnire.camera import Camera
from omnire.data.scene import SceneTime
from omnire.gaussians import Gaussians
from omnire.nodes.base import GaussianNode, GaussianNodeConfig, NodeContext, NodeOutput, init_gaussian_params
from omnire.pointcloud import colour_from_images, far_shell, knn_scales, points_in_box, to_tensor, voxel_downsample


@dataclasses.dataclass
class BackgroundConfig(GaussianNodeConfig):
    """Static background Gaussians."""

    _target: type = dataclasses.field(default_factory=lambda: BackgroundNode)
    voxel_size: float = 0.15
    """Voxel edge (m) for downsampling the accumulated LiDAR."""
    max_lidar_points: int = 150_000
    """Cap on LiDAR points after downsampling (random subset above it)."""
    num_far_points: int = 20_000
    """Random points in a far shell (1-3x the scene radius) for content beyond LiDAR."""
    num_random_points_without_lidar: int = 50_000
    """Points scattered in the camera frusta when the scene has no LiDAR."""
    ego_clearance: float = 1.5
    """LiDAR returns closer than this (m) to one of their frame's cameras are the recording
    vehicle itself (roof, mounts, camera housings) and seed no Gaussian (0: keep them)."""


def lidar_points_for_init(scene, frames: np.ndarray, excluded_tracks: list, ego_clearance: float = 1.5) -> np.ndarray:
    """(N,3) LiDAR of ``frames`` in the world, without points inside excluded tracks' boxes
    at that frame (those actors are modelled by their own nodes) and without the recording
    vehicle's returns: points closer than ``ego_clearance`` metres to one of the frame's
    cameras. Those sit where the cameras of other frames pass, so a Gaussian grown from one
    is seen by no training view that could correct it and fills a held-out view close to it."""
    if scene.lidar is None:
        return np.zeros((0, 3))
    chunks = []
    for f in frames:
        pts = scene.lidar.points[int(f)]
        if pts is None:
            continue
        keep = np.ones(len(pts), dtype=bool)
        for tr in excluded_tracks:
            if tr.present[int(f)]:
                keep &= ~points_in_box(pts, tr.poses[int(f)], tr.size, margin=0.1)
        if ego_clearance > 0 and len(pts):
            centres = np.stack([c.cam_to_world[int(f), :3, 3] for c in scene.cameras])  # (C, 3)
            centres = centres[np.isfinite(centres).all(axis=1)]
            if len(centres):
                nearest = np.linalg.norm(pts[:, None, :] - centres[None], axis=-1).min(axis=1)  # (n,)
                keep &= nearest >= ego_clearance
        chunks.append(pts[keep])
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def init_background_params(config: BackgroundConfig, context: NodeContext) -> dict[str, torch.Tensor]:
    """Raw Gaussian parameters for a static scene: LiDAR of the training frames (without
    points in the boxes of actors other nodes model), voxel-downsampled and capped, or
    random frustum points without LiDAR, plus a far shell; coloured from the images; scales
    from nearest neighbours. Shared by every node that starts from the static scene."""
    scene = context.scene
    rng = np.random.default_rng(int(torch.randint(0, 2**31, (1,), generator=context.generator)))
    pts = lidar_points_for_init(scene, scene.train_frames, context.excluded_tracks, config.ego_clearance)
    cams = np.stack([c.cam_to_world[f, :3, 3] for c in scene.cameras for f in scene.train_frames])
    center = cams.mean(0)
    if len(pts):
        pts = voxel_downsample(pts, config.voxel_size)
        if len(pts) > config.max_lidar_points:
            pts = pts[rng.choice(len(pts), config.max_lidar_points, replace=False)]
    else:
        pts = _frustum_points(scene, config.num_random_points_without_lidar, rng)
    ground = np.percentile(pts[:, 2], 5) if len(pts) else center[2] - 2.0
    far = far_shell(center, max(context.scene_radius, 30.0) * 2.0, config.num_far_points, rng, min_z=ground)
    all_pts = np.concatenate([pts, far]).astype(np.float32)
    colours, _ = colour_from_images(all_pts, scene, context.images, scene.train_frames)
    scales = knn_scales(all_pts)
    params = init_gaussian_params(
        to_tensor(all_pts), to_tensor(colours), to_tensor(scales), config.sh_degree, config.init_opacity, context.generator
    )
    return {k: v.to(context.device) for k, v in params.items()}


class BackgroundNode(GaussianNode):
    def __init__(self, config: BackgroundConfig, context: NodeContext, tracks: Optional[list] = None) -> None:
        super().__init__(config, context)
        self.init_gaussians(context, lambda: init_background_params(config, context))

    def gaussians_at(self, t: SceneTime, camera: Optional[Camera] = None,
                     step: Optional[int] = None) -> Optional[NodeOutput]:
        # all rows: the background is present at every moment
        return NodeOutput(Gaussians.from_params(self.gaussian_params), None, t)


def _frustum_points(scene, count: int, rng: np.random.Generator) -> np.ndarray:
    """Random points 2-60 m in front of the training cameras (no-LiDAR initialisation)."""
    out = []
    views = [(c, int(f)) for f in scene.train_frames for c in range(len(scene.cameras))]
    per = max(1, count // max(1, len(views)))
    for c, f in views:
        cam = scene.cameras[c]
        uv = rng.random((per, 2)) * [cam.width, cam.height]
        depth = 2.0 + 58.0 * rng.random(per) ** 2
        rays = np.concatenate([(uv - cam.intrinsics[:2, 2]) / np.diag(cam.intrinsics)[:2], np.ones((per, 1))], 1)
        p_cam = rays * depth[:, None]
        T = cam.cam_to_world[f]
        out.append(p_cam @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(out)
