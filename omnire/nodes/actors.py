"""Shared machinery of actor nodes (rigid, SMPL, deformable): one node object holds every
instance of its type; each Gaussian belongs to one instance (``instance`` buffer); each
instance has per-frame box poses, optionally refined.

Held-out frames never receive gradients, so their pose refinement is interpolated from the
nearest training frames of the same instance (linear in the small axis-angle / translation
deltas), and absent instances cost nothing: the rows of each instance are kept contiguous
(``instance`` non-decreasing; restored after densification through ``row_order``), so the
rows of the instances present at a frame are found from per-instance offsets without
scanning every Gaussian, gathered with a row-sparse gradient and stepped row-sparse by the
optimiser (:mod:`omnire.rowsparse`).
"""
from __future__ import annotations

import dataclasses
import warnings
from typing import Optional

import numpy as np
import torch
from torch import nn

from omnire.data.scene import ActorTrack, SceneData, SceneTime
from omnire.gaussians import GAUSSIAN_KEYS, Gaussians
from omnire.geometry import axis_angle_to_rotmat, quat_multiply, rotmat_to_quat, slerp_rotmats
from omnire.interpolation import bracket
from omnire.camera import Camera, gaussian_reach, may_be_drawn
from omnire.nodes.base import Derived, GaussianNode, MomentCache, GaussianNodeConfig, NodeContext, NodeOutput, ParamGroup
from omnire.placement import Placement
from omnire.pointcloud import points_in_box
from omnire.rowsparse import gather_rows


def frame_blend(t: SceneTime, num_frames: int) -> tuple[int, int, float]:
    """The recorded frames enclosing moment ``t`` and the weight of the second: (f0, f1, w);
    (f, f, 0.0) at a recorded frame."""
    if t.index is not None:
        return t.index, t.index, 0.0
    f0 = int(np.floor(t.frame))
    f1 = min(f0 + 1, num_frames - 1)
    return f0, f1, float(t.frame - f0)


def train_frame_bracket(train_frames: np.ndarray, num_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every frame 0..F-1, the training frames to interpolate learned per-frame values
    from (held-out frames get no gradient): (prev (F,), next (F,), weight (F,)); training
    frames map to themselves, frames outside the training span to the nearest one."""
    train = np.asarray(sorted(int(f) for f in train_frames))
    if len(train) == 0:
        f = np.arange(num_frames)
        return f, f, np.zeros(num_frames)
    i0, i1, w = bracket(train, np.arange(num_frames))
    return train[i0], train[i1], w


def usable_track(track: ActorTrack) -> bool:
    """False (with a warning naming the track) for tracks a box-based node cannot model."""
    if not np.all(np.isfinite(track.size)) or np.any(track.size <= 0):
        warnings.warn(f"track {track.track_id!r} ({track.class_name}): box size {track.size.tolist()} is not "
                      "positive; left to the background", stacklevel=2)
        return False
    if not track.present.any():
        warnings.warn(f"track {track.track_id!r} ({track.class_name}): present in no frame; skipped", stacklevel=2)
        return False
    return True


class ActorPoses(nn.Module):
    """Per-instance, per-frame box-to-world poses with optional learnable refinement.

    Buffers: base_R (I,F,3,3), base_t (I,F,3), present (I,F) bool. Parameters (when
    refining): delta_rot (I,F,3) axis-angle applied in the box frame, delta_t (I,F,3) in
    the world frame: pose = (R_base exp(delta_rot), t_base + delta_t).
    """

    def __init__(self, tracks: list[ActorTrack], train_frames: np.ndarray, refine: bool, device) -> None:
        super().__init__()
        I = len(tracks)
        F = tracks[0].poses.shape[0] if tracks else 0
        poses = np.stack([t.poses for t in tracks]) if tracks else np.zeros((0, F, 4, 4))
        present = np.stack([t.present for t in tracks]) if tracks else np.zeros((0, F), bool)
        poses = np.where(present[..., None, None], poses, np.eye(4))
        self.register_buffer("base_R", torch.as_tensor(poses[..., :3, :3], dtype=torch.float32, device=device))
        self.register_buffer("base_t", torch.as_tensor(poses[..., :3, 3], dtype=torch.float32, device=device))
        self.register_buffer("present", torch.as_tensor(present, device=device))
        self.refine = refine
        self.delta_rot = nn.Parameter(torch.zeros(I, F, 3, device=device), requires_grad=refine)
        self.delta_t = nn.Parameter(torch.zeros(I, F, 3, device=device), requires_grad=refine)
        # For each frame: the training frames to interpolate refinement from (prev, next, weight).
        prev_idx, next_idx, w = train_frame_bracket(train_frames, F)
        self.register_buffer("interp_prev", torch.tensor(prev_idx, dtype=torch.long, device=device), persistent=False)
        self.register_buffer("interp_next", torch.tensor(next_idx, dtype=torch.long, device=device), persistent=False)
        self.register_buffer("interp_w", torch.tensor(w, dtype=torch.float32, device=device), persistent=False)

    @property
    def num_instances(self) -> int:
        return self.present.shape[0]

    @property
    def num_frames(self) -> int:
        return self.present.shape[1]

    def at(self, t: SceneTime) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Poses of the instances present at moment ``t``: (ids (P,), R (P,3,3), t (P,3)).
        Between recorded frames an instance is present where it is at the nearer frame; its
        pose is SLERPed (rotation) and interpolated (translation) when it is present at both."""
        f0, f1, w = frame_blend(t, self.num_frames)
        if w == 0.0:
            return self.at_frame(f0)
        near = f0 if w < 0.5 else f1
        ids, R, tr = self.at_frame(near)
        both = self.present[ids, f0] & self.present[ids, f1]
        if bool(both.any()):
            sel = torch.nonzero(both).flatten()
            _, R0, t0 = self.at_frame(f0, ids[sel])
            _, R1, t1 = self.at_frame(f1, ids[sel])
            R = R.index_put((sel,), slerp_rotmats(R0, R1, torch.full((len(sel),), w, dtype=R0.dtype)))
            tr = tr.index_put((sel,), (1 - w) * t0 + w * t1)
        return ids, R, tr

    def at_frame(self, frame: int, ids: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Poses at recorded ``frame`` of the instances present there (or of ``ids``)."""
        if ids is None:
            ids = torch.nonzero(self.present[:, frame]).flatten()
        R, t = self.base_R[ids, frame], self.base_t[ids, frame]
        if self.refine:
            p, n, w = self.interp_prev[frame], self.interp_next[frame], self.interp_w[frame]
            d_rot = (1 - w) * self.delta_rot[ids, p] + w * self.delta_rot[ids, n]
            d_t = (1 - w) * self.delta_t[ids, p] + w * self.delta_t[ids, n]
            R = R @ axis_angle_to_rotmat(d_rot)
            t = t + d_t
        return ids, R, t

    def param_groups(self, lr_rot: float, lr_trans: float) -> list[ParamGroup]:
        if not self.refine or self.num_instances == 0:
            return []
        return [ParamGroup("box_rotation", [self.delta_rot], lr_rot),
                ParamGroup("box_translation", [self.delta_t], lr_trans)]


def instance_placement(instance: torch.Tensor, ids: torch.Tensor, R: torch.Tensor, t: torch.Tensor
                       ) -> Optional[Placement]:
    """The :class:`~omnire.placement.Placement` of box-local rows of the instances
    ``instance`` (M,) by the poses R (P,3,3), t (P,3) of ``ids`` (P,), when the rows are
    grouped by instance in the order of ``ids`` (as actor nodes gather them); else None."""
    lengths = segment_lengths(instance, ids)
    return None if lengths is None else Placement(lengths, R, t)


def transform_instances(g: Gaussians, instance: torch.Tensor, ids: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> Gaussians:
    """Move box-local Gaussians to the world: row i uses the pose of instance ``instance[i]``,
    looked up in ``ids`` (P,) with poses R (P,3,3), t (P,3). Quaternions are computed once
    per instance, not per Gaussian.

    Rows as actor nodes gather them (grouped by instance in the order of ``ids``) are moved
    one segment at a time (:meth:`Placement.apply`: no per-row copy of the poses, and pose
    gradients summed per segment by matrix products instead of scattered row by row); other
    row orders, and tensors off the CPU, take the per-row path (:func:`transform_rows`), which
    gives the same numbers."""
    placement = instance_placement(instance, ids, R, t)
    return transform_rows(g, instance, ids, R, t) if placement is None else placement.apply(g)


def placed_output(g: Gaussians, instance: torch.Tensor, ids: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                  rows: Optional[torch.Tensor], time: SceneTime, extras: Optional[dict] = None) -> NodeOutput:
    """A node output of box-local Gaussians ``g`` (rows of the instances ``instance``) put in
    the world by the poses R (P,3,3), t (P,3) of ``ids`` (P,): placed
    (:meth:`NodeOutput.placed`, the world copy made only if read) when the rows are grouped
    as actor nodes gather them, else moved now (:func:`transform_rows`)."""
    placement = instance_placement(instance, ids, R, t)
    if placement is None:
        return NodeOutput(transform_rows(g, instance, ids, R, t), rows, time, extras)
    return NodeOutput.placed(g, placement, rows, time, extras)


def transform_rows(g: Gaussians, instance: torch.Tensor, ids: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> Gaussians:
    """:func:`transform_instances` for rows in any order: each row gathers its pose."""
    lookup = torch.full((int(instance.max()) + 1 if len(instance) else 1,), -1, dtype=torch.long, device=ids.device)
    lookup[ids] = torch.arange(len(ids), device=ids.device)
    slot = lookup[instance]
    q = rotmat_to_quat(R)  # (P, 4)
    means = torch.einsum("nij,nj->ni", R[slot], g.means) + t[slot]
    return dataclasses.replace(g, means=means, quats=quat_multiply(q[slot], g.quats))


def segment_lengths(instance: torch.Tensor, ids: torch.Tensor) -> Optional[list[int]]:
    """Row counts of the instances ``ids`` (P,) when the rows ``instance`` (M,) are grouped
    by instance in the order of ``ids`` (both increasing, every row's instance in ``ids``),
    else None."""
    ids_increasing = len(ids) < 2 or bool((ids[1:] > ids[:-1]).all())
    if len(ids) == 0 or ids.device.type != "cpu" or not ids_increasing or not rows_grouped(instance):
        return None
    lengths = torch.searchsorted(instance, ids, right=True) - torch.searchsorted(instance, ids)
    if int(lengths.sum()) != len(instance):
        return None
    return lengths.tolist()


def rows_grouped(instance: torch.Tensor) -> bool:
    """True when ``instance`` (N,) is non-decreasing: each instance's rows are contiguous."""
    return len(instance) < 2 or not bool((instance[1:] < instance[:-1]).any())


def instance_offsets(instance: torch.Tensor, num_instances: int) -> torch.Tensor:
    """(I+1,) offsets of the contiguous rows of each instance in non-decreasing ``instance``
    (N,): instance i owns rows offsets[i]:offsets[i+1]."""
    if not rows_grouped(instance):
        raise ValueError("instance rows are not grouped (instance buffer must be non-decreasing)")
    return torch.searchsorted(instance, torch.arange(num_instances + 1, device=instance.device))


def segment_max(values: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """(I,) largest of ``values`` (N,) over each instance's rows, given ``offsets`` (I+1,)
    from :func:`instance_offsets`; 0 for an instance with no rows."""
    return torch.segment_reduce(values, "max", offsets=offsets, initial=0.0)


def segment_rows(offsets: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """Increasing rows (M,) of the instances ``ids`` (P,) increasing, given ``offsets`` (I+1,)
    from :func:`instance_offsets`; O(M), independent of the other instances' rows."""
    starts, ends = offsets[ids], offsets[ids + 1]
    lengths = ends - starts
    total = int(lengths.sum())
    if total == 0:
        return torch.zeros(0, dtype=torch.long, device=offsets.device)
    # row k of the output = starts[seg(k)] + (k - first output index of seg(k))
    seg = torch.repeat_interleave(torch.arange(len(ids), device=offsets.device), lengths)
    first_out = torch.cumsum(lengths, 0) - lengths
    return starts[seg] + torch.arange(total, device=offsets.device) - first_out[seg]


@dataclasses.dataclass
class ActorState:
    """Where a node's actors are at one moment: what :meth:`ActorNode.state_at` reads from
    the recorded (and refined) tracks, and what editing tools replace.

    Attributes:
        ids: (P,) increasing instance indices of the actors to draw.
        R: (P, 3, 3) box-to-world rotations; t: (P, 3) box centres in the world.
        body: (P, 24, 3, 3) body-joint rotations (SMPL order, root = orientation relative to
            the box) for nodes with a body model; None for the others (or "as recorded").
    """

    ids: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    body: Optional[torch.Tensor] = None

    def select(self, keep: torch.Tensor) -> "ActorState":
        """The actors ``keep`` picks: a (P,) bool mask or increasing indices (keeps the order)."""
        return ActorState(self.ids[keep], self.R[keep], self.t[keep], None if self.body is None else self.body[keep])


class ActorNode(GaussianNode):
    """Base of box-based actor nodes: one node object holds every instance of its type.

    Sets ``self.track_ids`` and ``self.poses`` (:class:`ActorPoses`, refined when
    ``refine_boxes``); subclasses set the per-Gaussian buffer ``instance`` (N,),
    non-decreasing (Gaussians of one instance are contiguous rows).

    Drawing is split in two: :meth:`state_at` says which actors are where at a moment (from
    the tracks), :meth:`gaussians_for` draws given actors in a given state. Simulation and
    viewers edit the state between the two.
    """

    poses: ActorPoses

    def __init__(self, config: GaussianNodeConfig, context: NodeContext, tracks: list[ActorTrack],
                 refine_boxes: bool) -> None:
        super().__init__(config, context)
        self.track_ids = [t.track_id for t in tracks]
        self.poses = ActorPoses(tracks, context.scene.train_frames, refine_boxes, context.device)
        self._offsets: Optional[tuple[torch.Tensor, torch.Tensor]] = None  # (instance tensor, offsets) cache
        self.reach_of_instances = Derived()  # (I,) what instance_reach indexes, kept while the parameters hold
        self.moment_outputs = MomentCache()  # renders' states and outputs by moment (gaussians_at)

    def instance_offsets(self) -> torch.Tensor:
        """(I+1,) row offsets per instance, recomputed only when the Gaussians change."""
        instance = self.gaussian_buffers["instance"]
        if self._offsets is None or self._offsets[0] is not instance:
            self._offsets = (instance, instance_offsets(instance, self.poses.num_instances))
        return self._offsets[1]

    def present_gaussians(self, ids: torch.Tensor) -> tuple[Gaussians, torch.Tensor]:
        """Box-local Gaussians of the instances ``ids`` (P,) increasing, and their rows (M,);
        gradients reach the parameters row-sparse (only these rows)."""
        rows = segment_rows(self.instance_offsets(), ids)
        return Gaussians(*(gather_rows(self.gaussian_params[k], rows) for k in GAUSSIAN_KEYS)), rows

    def placed_params(self, state: ActorState, time: SceneTime, extras: Optional[dict] = None) -> NodeOutput:
        """The node's box-local parameters placed by ``state`` (the actors ``state.ids`` at
        their poses), with nothing gathered: the placement's segments start at each actor's
        rows (:attr:`Placement.starts`), so a rasterizer that draws placed rows reads the
        parameters in place, and its gradients reach them row-sparse (only these rows). For
        nodes whose parameters are their box-local Gaussians as drawn (rigid actors)."""
        offsets = self.instance_offsets()
        starts, ends = offsets[state.ids], offsets[state.ids + 1]
        placement = Placement((ends - starts).tolist(), state.R, state.t, starts=starts.tolist())
        params = Gaussians(*(self.gaussian_params[k] for k in GAUSSIAN_KEYS))
        return NodeOutput.placed(params, placement, placement.rows, time, extras)

    def row_order(self) -> Optional[torch.Tensor]:
        instance = self.gaussian_buffers["instance"]
        return None if rows_grouped(instance) else torch.sort(instance, stable=True).indices

    def state_at(self, t: SceneTime) -> ActorState:
        """The actors present at ``t`` and their recorded (refined) poses."""
        ids, R, tr = self.poses.at(t)
        return ActorState(ids, R, tr)

    def gaussians_for(self, state: ActorState, t: SceneTime, camera: Optional[Camera] = None,
                      step: Optional[int] = None) -> Optional[NodeOutput]:
        """World-space Gaussians of the actors ``state.ids`` placed as ``state`` says, at
        moment ``t`` (for time-dependent appearance); None when ``state`` holds no actor."""
        raise NotImplementedError

    def instance_reach(self, state: ActorState) -> Optional[torch.Tensor]:
        """(P,) metres around each box centre ``state.t`` within which every Gaussian of the
        actors ``state.ids``, drawn in ``state``, lies together with its
        :func:`~omnire.camera.gaussian_reach`; None when the node cannot bound its Gaussians
        (nothing is culled)."""
        return None

    def in_view(self, state: ActorState, camera: Camera) -> ActorState:
        """``state`` without the actors of which ``camera`` can draw no Gaussian: their ball
        (:meth:`instance_reach`) is out of its view (:func:`omnire.camera.may_be_drawn`, the
        test the rasterizers' per-Gaussian culling passes), so the image is unchanged."""
        with torch.no_grad():
            reach = self.instance_reach(state)
            if reach is None:
                return state
            keep = may_be_drawn(state.t.detach(), reach, camera)
        return state if bool(keep.all()) else state.select(keep)

    def gaussians_at(self, t: SceneTime, camera: Optional[Camera] = None,
                     step: Optional[int] = None) -> Optional[NodeOutput]:
        """Renders (no autograd) leave out the actors ``camera`` cannot see (:meth:`in_view`)
        and keep what a moment needs (:attr:`moment_outputs`, emptied when a tensor of the
        node changes), so that the cameras of a rig rendered at one moment compute it once:
        the state at ``t``, the output of the actors a camera sees, and once a second camera
        at that moment sees other actors, the output of every present actor, which then
        serves every camera at that moment (the rasterizer culls the others per Gaussian: the
        same pixels up to the float rounding of batched pose products). So :meth:`gaussians_for` must not depend on ``camera`` beyond the actors
        it is given."""
        if torch.is_grad_enabled():
            # A training step places every present actor, so its Gaussians get their Adam
            # step on a zero gradient (momentum) as with dense Adam; skipping them changed
            # training (CHANGELOG.md, 2026-11-26). Nothing is kept.
            state = self.state_at(t)
            return None if len(state.ids) == 0 else self.gaussians_for(state, t, camera, step)
        kept = self.moment_outputs
        sources = (*self.parameters(), *self.buffers(), *self.gaussian_buffers.values())
        moment = (float(t.frame), float(t.seconds))
        state = kept.get(sources, ("state", moment), lambda: self.state_at(t))
        if len(state.ids) == 0:
            return None  # absent actors cost nothing
        every = ("every", moment, step)
        if kept.holds(sources, every):
            return kept.get(sources, every, lambda: None)
        seen = state if camera is None else self.in_view(state, camera)
        if len(seen.ids) == len(state.ids):
            return kept.get(sources, every, lambda: self.gaussians_for(state, t, camera, step))
        if len(seen.ids) == 0:  # present but out of view: no transform, no rasterizer rows
            g, rows = self.present_gaussians(seen.ids)  # no rows; the regularisers still run
            return NodeOutput(g, rows, t)
        key = ("seen", moment, step, tuple(seen.ids.tolist()))
        if not kept.holds(sources, key) and kept.holds(sources, ("drawn", moment, step)):
            return kept.get(sources, every, lambda: self.gaussians_for(state, t, None, step))
        kept.get(sources, ("drawn", moment, step), lambda: True)
        return kept.get(sources, key, lambda: self.gaussians_for(seen, t, camera, step))


@dataclasses.dataclass
class BoxActorConfig(GaussianNodeConfig):
    """Actors initialised from the LiDAR in their boxes, with refined per-frame box poses."""

    voxel_size: float = 0.05
    """Voxel edge (m) for the accumulated in-box LiDAR."""
    max_points_per_instance: int = 6000
    """Cap on LiDAR points per instance after downsampling."""
    random_points_per_instance: int = 300
    """Random points inside each box (covers surfaces LiDAR missed)."""
    max_init_scale: float = 0.2
    """Largest initial Gaussian scale (m)."""
    refine_boxes: bool = True
    """Learn per-frame box pose corrections (box refinement)."""
    lr_box_rotation: float = 1e-5
    """Box rotation refinement lr."""
    lr_box_translation: float = 5e-4
    """Box translation refinement lr."""


class BoxActorNode(ActorNode):
    """Actors whose Gaussians live in box-local space (rigid and deformable actors): built
    from :func:`init_box_gaussians`, with each box's half size as a buffer."""

    config: BoxActorConfig

    def __init__(self, config: BoxActorConfig, context: NodeContext, tracks: list[ActorTrack]) -> None:
        super().__init__(config, context, tracks, config.refine_boxes)
        instance: dict[str, torch.Tensor] = {}

        def build() -> dict[str, torch.Tensor]:
            params, instance["rows"] = init_box_gaussians(
                context, tracks, config.voxel_size, config.max_points_per_instance, config.random_points_per_instance,
                config.max_init_scale, config.sh_degree, config.init_opacity)
            return params

        self.init_gaussians(context, build)
        self.gaussian_buffers["instance"] = instance.get("rows", torch.zeros(0, dtype=torch.long, device=context.device))
        self.register_buffer("half_sizes", torch.as_tensor(np.stack([t.size for t in tracks]) / 2, dtype=torch.float32,
                                                           device=context.device))

    def param_groups(self) -> list[ParamGroup]:
        return super().param_groups() + self.poses.param_groups(self.config.lr_box_rotation,
                                                                 self.config.lr_box_translation)

    def instance_reach(self, state: ActorState) -> Optional[torch.Tensor]:
        """A box moves its Gaussians rigidly: the largest |box-local mean| + Gaussian reach
        over each actor's rows (0 for an actor with no rows); computed again only when the
        parameters change."""
        p = self.gaussian_params

        def every_instance() -> torch.Tensor:
            row_reach = p["means"].detach().norm(dim=-1) + gaussian_reach(p["scales"].detach())
            return segment_max(row_reach, self.instance_offsets())

        sources = (p["means"], p["scales"], self.gaussian_buffers["instance"])
        return self.reach_of_instances.get(sources, every_instance)[state.ids]


def box_local_lidar(scene: SceneData, track: ActorTrack, frames: np.ndarray, margin: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR points inside the track's box over ``frames``, in box-local coordinates (N,3),
    with the frame each came from (N,)."""
    pts, src = [], []
    if scene.lidar is None:
        return np.zeros((0, 3)), np.zeros(0, int)
    for f in frames:
        f = int(f)
        if not track.present[f] or scene.lidar.points[f] is None:
            continue
        p = scene.lidar.points[f]
        inside = points_in_box(p, track.poses[f], track.size, margin)
        if inside.any():
            local = (p[inside] - track.poses[f][:3, 3]) @ track.poses[f][:3, :3]
            pts.append(local)
            src.append(np.full(len(local), f))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, int)
    return np.concatenate(pts), np.concatenate(src)


def visible_in_cameras(track: ActorTrack, scene: SceneData, frames: Optional[np.ndarray] = None, margin: float = 0.1) -> bool:
    """True when the track's box centre or a corner projects inside some camera at some of
    ``frames`` (default: training frames) in front of it. Actors no camera sees get no node."""
    frames = scene.train_frames if frames is None else frames
    corners = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)] + [[0, 0, 0]]) * track.size
    for f in frames:
        f = int(f)
        if not track.present[f]:
            continue
        world = corners @ track.poses[f][:3, :3].T + track.poses[f][:3, 3]
        for cam in scene.cameras:
            w2c = np.linalg.inv(cam.cam_to_world[f])
            p = world @ w2c[:3, :3].T + w2c[:3, 3]
            front = p[:, 2] > 0.5
            if not front.any():
                continue
            uv = p[front, :2] / p[front, 2:] @ cam.intrinsics[:2, :2].T + cam.intrinsics[:2, 2]
            mw, mh = margin * cam.width, margin * cam.height
            if np.any((uv[:, 0] > -mw) & (uv[:, 0] < cam.width + mw) & (uv[:, 1] > -mh) & (uv[:, 1] < cam.height + mh)):
                return True
    return False


def seen_by_lidar(track: ActorTrack, scene: SceneData, frames: Optional[np.ndarray] = None,
                  min_returns: int = 10) -> bool:
    """True when some sweep of ``frames`` (default: training frames) has at least
    ``min_returns`` LiDAR returns inside the track's box: a 360-degree sensor measures actors
    that no camera sees (behind or beside the car)."""
    if scene.lidar is None:
        return False
    frames = scene.train_frames if frames is None else frames
    for f in frames:
        f = int(f)
        points = scene.lidar.points[f]
        if not track.present[f] or points is None:
            continue
        if int(points_in_box(points, track.poses[f], track.size).sum()) >= min_returns:
            return True
    return False


def observed_in_training(track: ActorTrack, scene: SceneData, lidar_learning: bool) -> bool:
    """Whether training sees the actor at all: a camera does, or, when LiDAR is learned as a
    sensor (``--method.lidar.enabled``), the LiDAR does. Actors training never sees stay in
    the background (no node, no cost); a LiDAR-only actor there would be static Gaussians
    where the sweeps saw it move."""
    return visible_in_cameras(track, scene) or (lidar_learning and seen_by_lidar(track, scene))


def colour_box_points(scene: SceneData, images, track: ActorTrack, local: np.ndarray, src: np.ndarray) -> np.ndarray:
    """Colours (N,3) of box-local points, each projected into the images of the frame it
    came from (src (N,); -1 = use every frame the track is present in)."""
    from omnire.pointcloud import colour_from_images

    colours = np.full((len(local), 3), 0.5, dtype=np.float32)
    for f in np.unique(src):
        sel = src == f
        frames = np.array([f]) if f >= 0 else np.intersect1d(track.frames(), scene.train_frames)
        if len(frames) == 0:
            continue
        ref = int(frames[len(frames) // 2])
        world = local[sel] @ track.poses[ref][:3, :3].T + track.poses[ref][:3, 3]
        colours[sel], _ = colour_from_images(world, scene, images, np.array([ref]))
    return colours


def track_displacement(track: ActorTrack) -> float:
    """Largest distance (m) between the box centres of any two frames the actor is present."""
    c = track.poses[track.present][:, :3, 3]
    if len(c) < 2:
        return 0.0
    return float(np.linalg.norm(c - c[0], axis=1).max() + np.linalg.norm(c - c.mean(0), axis=1).max())


def init_box_gaussians(context, tracks: list[ActorTrack], voxel_size: float, max_points: int, random_points: int,
                       max_scale: float, sh_degree: int, init_opacity: float) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Box-local Gaussians for every instance: the LiDAR inside its box over the training
    frames (accumulated in the box frame, voxel-downsampled, capped at ``max_points``) plus
    ``random_points`` uniform in the box, coloured from the images, isotropic scales from
    nearest neighbours (at most ``max_scale``). Returns raw parameters and the owning
    instance of each Gaussian (N,)."""
    from omnire.nodes.base import init_gaussian_params
    from omnire.pointcloud import knn_scales, to_tensor, voxel_downsample

    scene = context.scene
    rng = np.random.default_rng(int(torch.randint(0, 2**31, (1,), generator=context.generator)))
    points, colours, owners = [], [], []
    for i, track in enumerate(tracks):
        local, _ = box_local_lidar(scene, track, scene.train_frames)
        if len(local):
            local = voxel_downsample(local, voxel_size)
        if len(local) > max_points:
            local = local[rng.choice(len(local), max_points, replace=False)]
        local = np.concatenate([local, (rng.random((random_points, 3)) - 0.5) * track.size])
        # merged voxels: colour from every frame the box is seen in
        colours.append(colour_box_points(scene, context.images, track, local, np.full(len(local), -1)))
        points.append(local)
        owners.append(np.full(len(local), i))
    scales = np.concatenate([np.minimum(knn_scales(p), max_scale) for p in points])
    params = init_gaussian_params(to_tensor(np.concatenate(points)), to_tensor(np.concatenate(colours)),
                                  to_tensor(scales), sh_degree, init_opacity, context.generator)
    instance = torch.as_tensor(np.concatenate(owners), dtype=torch.long, device=context.device)
    return {k: v.to(context.device) for k, v in params.items()}, instance
