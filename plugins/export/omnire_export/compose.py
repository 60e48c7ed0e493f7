"""The scene at one moment as parts: each actor in its own (box) frame with its pose, every
other Gaussian node in the world frame.

Actors are drawn by their node (:meth:`ActorNode.gaussians_for`) at the identity pose, which
gives their Gaussians in the box frame at that moment (posed and skinned for pedestrians,
deformed for deformable actors); the world Gaussians are then ``R x + t`` for the means and
``q(R) * q`` for the rotations (the same transform every actor node applies last).
:func:`compose` does that arithmetic in float64 from the float32 pose and the quaternion
stored with it, elementwise in a fixed order, so a whole-scene export and a per-node export
recomposed with its pose file give the same float32 bits.
"""
from __future__ import annotations

import dataclasses
from typing import Iterator, Optional

import numpy as np
import torch

from omnire.api import ActorNode, ActorState, Gaussians, SceneTime, rotmat_to_quat


@dataclasses.dataclass(frozen=True)
class Pose:
    """A box-to-world pose as the runtime holds it.

    Attributes:
        R: (3, 3) float32 rotation; t: (3,) float32 box centre in the world.
        quat: (4,) float64 wxyz of ``R`` (w >= 0), the rotation applied to the Gaussians'
            quaternions.
    """

    R: np.ndarray
    t: np.ndarray
    quat: np.ndarray

    @classmethod
    def from_rt(cls, R: np.ndarray, t: np.ndarray) -> "Pose":
        R = np.asarray(R, dtype=np.float32)
        return cls(R, np.asarray(t, dtype=np.float32), np.asarray(rotmat_to_quat(R.astype(np.float64)), np.float64))

    def to_json(self) -> dict:
        """Exact values (float32 and float64 print and parse back bit for bit)."""
        return {"R": [[float(v) for v in row] for row in self.R], "t": [float(v) for v in self.t],
                "quat_wxyz": [float(v) for v in self.quat]}

    @classmethod
    def from_json(cls, data: dict) -> "Pose":
        return cls(np.asarray(data["R"], np.float32), np.asarray(data["t"], np.float32),
                   np.asarray(data["quat_wxyz"], np.float64))


def quat_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of wxyz quaternions, (..., 4) each, in the order written."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def compose(means: np.ndarray, quats: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Box-frame means (n, 3) and quaternions (n, 4) -> world (float32 each): means
    ``R x + t`` and quaternions ``q(R) * q``, computed in float64."""
    m = means.astype(np.float64)
    R = pose.R.astype(np.float64)
    world = m[:, 0:1] * R[:, 0] + m[:, 1:2] * R[:, 1] + m[:, 2:3] * R[:, 2] + pose.t.astype(np.float64)
    q = quat_product(pose.quat[None, :], quats.astype(np.float64))
    return world.astype(np.float32), q.astype(np.float32)


@dataclasses.dataclass
class Part:
    """Gaussians of one node (world frame, ``pose`` None) or of one actor (its box frame at
    the moment, placed in the world by ``pose``); ``lidar``: their LiDAR features (n, 2)
    when the scene learned them (omnire/lidarmodel.py)."""

    node: str
    gaussians: Gaussians
    track_id: Optional[str] = None
    instance: Optional[int] = None
    pose: Optional[Pose] = None
    lidar: Optional[torch.Tensor] = None

    def __len__(self) -> int:
        return len(self.gaussians)

    def arrays(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Rows start:stop as numpy arrays in the world frame (``GAUSSIAN_KEYS`` names, and
        ``lidar`` when the part has LiDAR features)."""
        out = self.local_arrays(start, stop)
        if self.pose is not None:
            out["means"], out["quats"] = compose(out["means"], out["quats"], self.pose)
        return out

    def local_arrays(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Rows start:stop in the part's own frame (the box frame for actors)."""
        g = self.gaussians
        out = {k: getattr(g, k)[start:stop].detach().cpu().numpy() for k in
               ("means", "quats", "scales", "opacities", "sh0", "shN")}
        if self.lidar is not None:
            out["lidar"] = self.lidar[start:stop].detach().cpu().numpy()
        return out


def actor_batches(node: ActorNode, ids: torch.Tensor, max_rows: int) -> list[torch.Tensor]:
    """``ids`` (P,) split into consecutive groups of at most ``max_rows`` Gaussians (a single
    larger actor forms its own group), so drawing one group bounds the memory used."""
    offsets = node.instance_offsets()
    counts = (offsets[ids + 1] - offsets[ids]).tolist()
    groups, start, rows = [], 0, 0
    for k, c in enumerate(counts):
        if k > start and rows + c > max_rows:
            groups.append(ids[start:k])
            start, rows = k, 0
        rows += c
    if start < len(counts):
        groups.append(ids[start:])
    return groups


def local_state(state: ActorState, sel: torch.Tensor) -> ActorState:
    """The actors ``state.ids[sel]`` at the identity pose (body rotations kept)."""
    P = len(sel)
    R = torch.eye(3, dtype=state.R.dtype, device=state.R.device).expand(P, 3, 3).contiguous()
    t = torch.zeros(P, 3, dtype=state.t.dtype, device=state.t.device)
    return ActorState(state.ids[sel], R, t, None if state.body is None else state.body[sel])


def actor_parts(name: str, node: ActorNode, t: SceneTime, state: ActorState, max_rows: int) -> Iterator[Part]:
    """One :class:`Part` per actor of ``state`` (in id order), drawn in groups of at most
    ``max_rows`` Gaussians."""
    if len(state.ids) == 0:
        return
    position = {int(i): k for k, i in enumerate(state.ids.tolist())}
    for group in actor_batches(node, state.ids, max_rows):
        sel = torch.as_tensor([position[int(i)] for i in group.tolist()], dtype=torch.long)
        out = node.gaussians_for(local_state(state, sel), t)
        if out is None:
            continue
        if out.rows is None:
            raise ValueError(f"node {name!r}: gaussians_for returned no rows; cannot tell its actors apart")
        instance = node.gaussian_buffers["instance"][out.rows]
        lidar = node.lidar_features(out)
        ids, counts = torch.unique_consecutive(instance, return_counts=True)
        start = 0
        for i, c in zip(ids.tolist(), counts.tolist(), strict=True):
            k = position[int(i)]
            g = Gaussians(*(getattr(out.gaussians, f)[start:start + c] for f in
                            ("means", "quats", "scales", "opacities", "sh0", "shN")))
            pose = Pose.from_rt(state.R[k].detach().cpu().numpy(), state.t[k].detach().cpu().numpy())
            yield Part(name, g, node.track_ids[int(i)], int(i), pose,
                       None if lidar is None else lidar[start:start + c])
            start += c


def scene_parts(recon, t: SceneTime, max_rows: int = 1 << 16, hidden: frozenset[str] = frozenset()) -> Iterator[Part]:
    """Every Gaussian node of ``recon`` (a :class:`~omnire.api.Reconstruction`) present at
    ``t``, in the order the runtime draws them (``Reconstruction.drawn``): a node without
    actors as one world-frame part, actor nodes as one part per actor. Environment nodes
    hold no Gaussians and are not drawn."""
    for drawn in recon.drawn(t, hidden=hidden):
        if drawn.is_actor:
            yield from actor_parts(drawn.node_name, drawn.node, drawn.moment, drawn.state, max_rows)
        else:
            out = drawn.output()
            if out is not None and len(out.gaussians):
                yield Part(drawn.node_name, out.gaussians, lidar=drawn.node.lidar_features(out))
