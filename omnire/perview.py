"""Learned values per recorded (camera, frame): the shared part of exposure compensation
(omnire/exposure.py) and camera-pose refinement (omnire/camerapose.py).

Each training (camera, frame) owns one entry of ``delta`` (C, F, *shape), learned from zero.
Held-out frames get no gradient, so a recorded camera's value at any moment is interpolated
linearly from the training frames around it (the same bracketing as actor pose refinement),
and a camera the log did not record (no name, or a name the scene does not have, e.g. a
synthetic viewpoint) has none.

The entries are rows of one (C * F, *shape) parameter read through
:func:`omnire.rowsparse.gather_rows`, so a step's gradient is row-sparse and Adam steps only
the rows the rendered view used (lazy Adam, as for actors): with a dense step, momentum
would keep moving every other view's entry for steps after it was last rendered.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import nn

from omnire.data.scene import SceneTime
from omnire.nodes.actors import frame_blend, train_frame_bracket
from omnire.nodes.base import ParamGroup
from omnire.rowsparse import gather_rows


class PerViewParameter(nn.Module):
    """A learned correction per recorded (camera, frame), zero at the start.

    Attributes:
        delta: (C * F, *shape) parameter, row ``camera * F + frame``.
        group: name of its optimiser parameter group.
    """

    group: str = "per_view"

    def __init__(self, camera_names: list[str], num_frames: int, train_frames: np.ndarray, shape: tuple[int, ...],
                 lr: float, device: torch.device) -> None:
        super().__init__()
        self.camera_index = {name: i for i, name in enumerate(camera_names) if name}
        self.num_cameras = len(camera_names)
        self.num_frames = num_frames
        self.lr = lr
        self.delta = nn.Parameter(torch.zeros(len(camera_names) * num_frames, *shape, device=device))
        self.interp = train_frame_bracket(train_frames, num_frames)  # (prev, next, weight), each (F,)

    @property
    def per_view(self) -> torch.Tensor:
        """``delta`` as (C, F, *shape)."""
        return self.delta.view(self.num_cameras, self.num_frames, *self.delta.shape[1:])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints written before the rows were flattened hold (C, F, *shape)
        key = prefix + "delta"
        if key in state_dict and state_dict[key].dim() == self.delta.dim() + 1:
            state_dict[key] = state_dict[key].flatten(0, 1)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def delta_at(self, camera_name: str, t: SceneTime) -> Optional[torch.Tensor]:
        """(*shape) value for camera ``camera_name`` at moment ``t``, or None for a camera
        the scene did not record."""
        cam = self.camera_index.get(camera_name)
        if cam is None:
            return None
        f0, f1, w = frame_blend(t, self.num_frames)
        prev, nxt, bw = self.interp
        weights: dict[int, float] = {}  # row -> weight, summing to 1 (a training frame is its own bracket)
        for frame, fw in ((f0, 1.0 - w), (f1, w)):
            for f, ww in ((int(prev[frame]), 1.0 - float(bw[frame])), (int(nxt[frame]), float(bw[frame]))):
                if fw * ww != 0.0:
                    row = cam * self.num_frames + f
                    weights[row] = weights.get(row, 0.0) + fw * ww
        rows = sorted(weights)
        values = gather_rows(self.delta, torch.tensor(rows, dtype=torch.long, device=self.delta.device))
        if len(rows) == 1 and weights[rows[0]] == 1.0:
            return values[0]
        w_rows = torch.tensor([weights[r] for r in rows], dtype=values.dtype, device=values.device)
        return (w_rows.view(-1, *[1] * (values.dim() - 1)) * values).sum(0)

    def regularization(self, camera_name: str, t: SceneTime) -> Optional[torch.Tensor]:
        """Mean squared entry of the correction a view of ``camera_name`` at ``t`` uses (keeps
        what every view shares out of them; only the rows that view reads get a gradient),
        None for an unrecorded camera."""
        d = self.delta_at(camera_name, t)
        return None if d is None else (d ** 2).mean()

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup(self.group, [self.delta], self.lr)]
