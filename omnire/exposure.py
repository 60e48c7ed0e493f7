"""Per-camera, per-frame exposure: a learned affine colour transform of each rendered image.

The cameras of a rig differ in exposure and white balance, and auto-exposure drifts over a
log (PandaSet's front_left camera renders visibly warmer than its neighbours). Without a
correction, Gaussians seen by several cameras or frames average those differences into their
colours. As in the reference implementation and its peers (an affine transform per image),
each training (camera, frame) gets

    rgb' = (I + D[:, :3]) rgb + D[:, 3],    D (3, 4) learned from zero,

applied to the composited image (Gaussians and sky). Held-out frames get no gradient, so a
recorded camera's transform at any moment is interpolated linearly from the training frames
around it (the same bracketing as actor pose refinement); a camera the log did not record (no
name, or a name the scene does not have, e.g. a synthetic viewpoint) is rendered untransformed.
An L2 penalty on D (regulariser ``exposure``) keeps the scene's colours in the Gaussians: a
transform shared by every image would otherwise be free to drift.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import nn

from omnire.data.scene import SceneTime
from omnire.nodes.actors import frame_blend, train_frame_bracket
from omnire.nodes.base import ParamGroup


class ExposureCompensation(nn.Module):
    """Affine colour transforms per (camera, frame) of a scene. See the module docstring.

    Attributes:
        delta: (C, F, 3, 4) parameter, the transform minus identity per camera and frame.
    """

    def __init__(self, camera_names: list[str], num_frames: int, train_frames: np.ndarray, lr: float,
                 device: torch.device) -> None:
        super().__init__()
        self.camera_index = {name: i for i, name in enumerate(camera_names) if name}
        self.num_frames = num_frames
        self.lr = lr
        self.delta = nn.Parameter(torch.zeros(len(camera_names), num_frames, 3, 4, device=device))
        prev_idx, next_idx, w = train_frame_bracket(train_frames, num_frames)
        self.register_buffer("interp_prev", torch.tensor(prev_idx, dtype=torch.long, device=device), persistent=False)
        self.register_buffer("interp_next", torch.tensor(next_idx, dtype=torch.long, device=device), persistent=False)
        self.register_buffer("interp_w", torch.tensor(w, dtype=torch.float32, device=device), persistent=False)

    def _at_frame(self, cam: int, frame: int) -> torch.Tensor:
        """(3, 4) delta at recorded ``frame`` (interpolated from training frames)."""
        p, n, w = self.interp_prev[frame], self.interp_next[frame], self.interp_w[frame]
        return (1 - w) * self.delta[cam, p] + w * self.delta[cam, n]

    def delta_at(self, camera_name: str, t: SceneTime) -> Optional[torch.Tensor]:
        """(3, 4) transform minus identity for camera ``camera_name`` at moment ``t``, or None
        for a camera the scene did not record."""
        cam = self.camera_index.get(camera_name)
        if cam is None:
            return None
        f0, f1, w = frame_blend(t, self.num_frames)
        d = self._at_frame(cam, f0)
        return d if w == 0.0 else (1 - w) * d + w * self._at_frame(cam, f1)

    def apply(self, rgb: torch.Tensor, camera_name: str, t: SceneTime) -> torch.Tensor:
        """(H, W, 3) rendered colour -> the recorded camera's colour at ``t``."""
        d = self.delta_at(camera_name, t)
        if d is None:
            return rgb
        return rgb + rgb @ d[:, :3].T + d[:, 3]

    def regularization(self) -> torch.Tensor:
        """Mean squared entry of the transforms' deviation from identity."""
        return (self.delta ** 2).mean()

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup("exposure", [self.delta], self.lr)]
