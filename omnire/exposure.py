"""Per-camera, per-frame exposure: a learned affine colour transform of each rendered image.

The cameras of a rig differ in exposure and white balance, and auto-exposure drifts over a
log (PandaSet's front_left camera renders visibly warmer than its neighbours). Without a
correction, Gaussians seen by several cameras or frames average those differences into their
colours. As in the reference implementation and its peers (an affine transform per image),
each training (camera, frame) gets

    rgb' = (I + D[:, :3]) rgb + D[:, 3],    D (3, 4) learned from zero,

applied to the composited image (Gaussians and sky). Held-out frames interpolate, unrecorded
cameras are rendered untransformed (omnire/perview.py). An L2 penalty on D (regulariser
``exposure``) keeps the scene's colours in the Gaussians: a transform shared by every image
would otherwise be free to drift.
"""
from __future__ import annotations

import numpy as np
import torch

from omnire.data.scene import SceneTime
from omnire.perview import PerViewParameter


class ExposureCompensation(PerViewParameter):
    """Affine colour transforms per (camera, frame) of a scene. See the module docstring.

    Attributes:
        delta: (C * F, 3, 4) parameter, the transform minus identity per camera and frame.
    """

    group = "exposure"

    def __init__(self, camera_names: list[str], num_frames: int, train_frames: np.ndarray, lr: float,
                 device: torch.device) -> None:
        super().__init__(camera_names, num_frames, train_frames, (3, 4), lr, device)

    def apply(self, rgb: torch.Tensor, camera_name: str, t: SceneTime) -> torch.Tensor:
        """(H, W, 3) rendered colour -> the recorded camera's colour at ``t``."""
        d = self.delta_at(camera_name, t)
        if d is None:
            return rgb
        # one fused product rgb (I + D3)^T + D4: the CPU's matrix library is slow on a
        # (H W, 3) x (3, 3) product, and separate adds cost two more passes over the image
        eye = torch.eye(3, dtype=d.dtype, device=d.device)
        return torch.nn.functional.linear(rgb, eye + d[:, :3], d[:, 3])
