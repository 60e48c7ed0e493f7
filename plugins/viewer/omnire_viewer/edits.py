"""Hiding and moving actors: the viewer's one seam to scene editing.

Actor nodes split drawing in two (:meth:`ActorNode.state_at`: where the tracks put the
actors at a moment; :meth:`ActorNode.gaussians_for`: draw given actors in a given state).
An edit replaces the state between the two: :func:`apply_edits` is the only place the
viewer changes what is drawn, and both the browser objects and the server render go
through it. When the simulation edit model (``omnire sim``, plugins/sim) lands, this
function is what to point at it; until then it implements hide and move itself.
"""
from __future__ import annotations

import dataclasses
import math

import torch

from omnire.api import ActorNode, ActorState, SceneTime


@dataclasses.dataclass(frozen=True)
class ActorEdit:
    """One actor's edit.

    Attributes:
        hidden: not drawn at all.
        offset: (3,) metres added to the box centre, world frame (x, y, z up).
        yaw: radians about the world vertical through the box centre.
    """

    hidden: bool = False
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0

    @property
    def is_identity(self) -> bool:
        return not self.hidden and not any(self.offset) and self.yaw == 0.0


class EditModel:
    """Edits by track id (track ids are unique in a scene)."""

    def __init__(self) -> None:
        self._edits: dict[str, ActorEdit] = {}

    def get(self, track_id: str) -> ActorEdit:
        return self._edits.get(track_id, ActorEdit())

    def set(self, track_id: str, edit: ActorEdit) -> None:
        if edit.is_identity:
            self._edits.pop(track_id, None)
        else:
            self._edits[track_id] = edit

    def clear(self) -> None:
        self._edits.clear()

    def __bool__(self) -> bool:
        return bool(self._edits)

    def items(self):
        return self._edits.items()


def yaw_matrix(angle: float, dtype=torch.float32, device="cpu") -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def apply_edits(edits: EditModel, node: ActorNode, state: ActorState, t: SceneTime) -> ActorState:
    """The state ``node`` draws at ``t`` after ``edits``: hidden actors are dropped, moved
    ones turned by their yaw about their box centre and shifted by their offset
    (R' = Rz(yaw) R, t' = t + offset). Returns ``state`` itself when nothing applies."""
    if not edits or len(state.ids) == 0:
        return state
    track_ids = [node.track_ids[i] for i in state.ids.tolist()]
    if not any(not edits.get(tid).is_identity for tid in track_ids):
        return state
    keep = [k for k, tid in enumerate(track_ids) if not edits.get(tid).hidden]
    sel = torch.as_tensor(keep, dtype=torch.long, device=state.ids.device)
    R, tr = state.R[sel].clone(), state.t[sel].clone()
    for row, k in enumerate(keep):
        edit = edits.get(track_ids[k])
        if edit.yaw:
            R[row] = yaw_matrix(edit.yaw, R.dtype, R.device) @ R[row]
        if any(edit.offset):
            tr[row] = tr[row] + torch.as_tensor(edit.offset, dtype=tr.dtype, device=tr.device)
    return ActorState(state.ids[sel], R, tr, None if state.body is None else state.body[sel])
