"""Method presets: which node types, which losses with which weights, densification.

A method is a :class:`MethodConfig`; plugins register named presets through
``omnire_register_methods``. ``nodes`` maps node-type names (from the node-type registry)
to their configs; actor tracks are assigned to the enabled node types that declare their
category (highest priority wins), so the core never tests class or node names.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from omnire.lidarmodel import LidarConfig
from omnire.strategy import DensifyConfig


@dataclasses.dataclass
class MethodConfig:
    """A reconstruction method."""

    nodes: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Enabled node types and their configs (node-type name -> config)."""
    disable: tuple[str, ...] = ()
    """Node types of this method to switch off (ablations, e.g. --method.disable smpl); their
    actors go to the next enabled node type that takes them, else the background."""
    loss_weights: dict[str, float] = dataclasses.field(
        default_factory=lambda: {"l1": 0.8, "dssim": 0.2, "depth": 0.1}
    )
    """Loss term weights by registered loss name (0 disables a term)."""
    regularization_weights: dict[str, float] = dataclasses.field(default_factory=dict)
    """Weights of node regularisers by name (e.g. pose smoothness)."""
    dynamic_pixel_weight: float = 1.0
    """Image-loss weight on pixels of dynamic actors (the paper uses 5)."""
    densify: DensifyConfig = dataclasses.field(default_factory=DensifyConfig)
    """AbsGrad densification."""
    sh_degree_interval: int = 1000
    """Steps between switching on SH bands."""
    num_downscales: int = 0
    """Coarse-to-fine: the first steps train at 1 / 2**num_downscales of the image resolution
    (0 = full resolution throughout; see omnire/resolution.py)."""
    resolution_schedule: int = 250
    """Steps per resolution level: the downscale factor halves every this many steps."""
    exposure: bool = True
    """Learn an affine colour transform per camera and training frame (omnire/exposure.py);
    --method.no-exposure renders the Gaussians' colours as they are."""
    exposure_lr: float = 1e-3
    """Adam lr of the exposure transforms."""
    exposure_weight: float = 1e-2
    """Weight of the L2 penalty on the transforms' deviation from identity."""
    camera_pose_refinement: bool = True
    """Learn a rigid correction of each recorded camera pose per training frame
    (omnire/camerapose.py; held-out frames interpolate it); --method.no-camera-pose-refinement
    renders from the recorded poses."""
    camera_pose_lr: float = 1e-4
    """Adam lr of the pose corrections (rad for rotations, m for translations)."""
    camera_pose_weight: float = 1e-2
    """Weight of the L2 penalty on the pose corrections."""
    background_color: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour under the Gaussians when the method has no environment (sky) node."""
    cull_to_view: bool = True
    """Drop Gaussians whose 3-sigma extent lies outside the camera frustum before colour
    evaluation and rasterization (same image, less work; their rows get no optimiser step),
    and let nodes skip what the camera cannot see (actors out of view, in renders without
    autograd; deformablegs' canonical Gaussians beyond its cull margin)."""
    lidar: LidarConfig = dataclasses.field(default_factory=LidarConfig)
    """LiDAR as a rendered sensor (omnire/lidarmodel.py): off by default; --method.lidar.enabled
    learns per-Gaussian intensity and ray drop and trains on rendered sweeps."""
    rasterizer: str = "auto"
    """Rasterizer backend name, or auto (gsplat on CUDA, native on CPU, else torch)."""
