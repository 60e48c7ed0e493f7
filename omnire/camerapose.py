"""Camera-pose refinement: a learned rigid correction of each recorded camera pose.

Recorded camera poses (ego pose x calibration, time-synchronised) are off by millimetres
and hundredths of a degree, enough to blur what several views see. As in the reference
implementation and its peers, each training (camera, frame) gets a small SE(3) correction
learned from zero,

    C' = C @ [R(r) | t],    delta = (r (3,) axis-angle in rad, t (3,) in m), camera frame,

held-out frames interpolate it and unrecorded cameras get none (omnire/perview.py). The
rasterizers take no gradient with respect to the camera, so the correction is applied to
the scene instead: the recorded camera C sees ``A x`` exactly as C' sees ``x``, with
``A = C delta^-1 C^-1`` (:meth:`CameraPoseRefinement.world_transform`), and autograd carries
the image gradient through the Gaussians' means and rotations to ``delta``. (SH colours are
not rotated by A, a second-order effect for corrections this small.) An L2 penalty
(regulariser ``camera_pose``) keeps a shift every view shares out of the corrections.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from omnire.camera import Camera
from omnire.data.scene import SceneTime
from omnire.geometry import axis_angle_to_rotmat
from omnire.perview import PerViewParameter


class CameraPoseRefinement(PerViewParameter):
    """SE(3) corrections per (camera, frame) of a scene. See the module docstring.

    Attributes:
        delta: (C * F, 6) parameter: axis-angle (rad) then translation (m), camera frame.
    """

    group = "camera_pose"

    def __init__(self, camera_names: list[str], num_frames: int, train_frames: np.ndarray, lr: float,
                 device: torch.device) -> None:
        super().__init__(camera_names, num_frames, train_frames, (6,), lr, device)

    def correction(self, camera: Camera, t: SceneTime) -> Optional[torch.Tensor]:
        """(4, 4) correction [R | t] of ``camera`` at ``t`` (C' = C @ it), or None."""
        d = self.delta_at(camera.name, t)
        if d is None:
            return None
        top = torch.cat([axis_angle_to_rotmat(d[:3]), d[3:, None]], dim=1)
        return torch.cat([top, torch.eye(4, dtype=top.dtype, device=top.device)[3:]], dim=0)

    def refined_camera(self, camera: Camera, t: SceneTime) -> Camera:
        """``camera`` at its refined pose (unchanged for an unrecorded camera)."""
        delta = self.correction(camera, t)
        if delta is None:
            return camera
        return Camera(camera.K, camera.cam_to_world @ delta.detach(), camera.width, camera.height, camera.name)

    def world_transform(self, camera: Camera, t: SceneTime) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
        """(R (3, 3), t (3,)) of ``A = C delta^-1 C^-1``: the recorded camera C sees ``R x + t``
        as the refined camera sees ``x``. None for an unrecorded camera."""
        d = self.delta_at(camera.name, t)
        if d is None:
            return None
        R_d, t_d = axis_angle_to_rotmat(d[:3]), d[3:]
        R_c, t_c = camera.cam_to_world[:3, :3].to(d), camera.cam_to_world[:3, 3].to(d)
        R_a = R_c @ R_d.T @ R_c.T
        return R_a, t_c - R_a @ t_c - R_c @ (R_d.T @ t_d)
