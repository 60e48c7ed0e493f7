"""Rendering an edited scene: a :class:`Simulation` resolves a :class:`Scenario` against a
:class:`~omnire.api.Reconstruction` (and the runs its insertions come from) and renders any
camera at any moment.

How an edit reaches the pixels (the actor nodes' seam, ``ActorNode.state_at`` ->
``gaussians_for``): per actor node, the recorded state at the scene moment is read, the
edited actors are taken out of it (removed ones are dropped), the rest is drawn as
recorded, and each edited actor is drawn by its node's ``gaussians_for`` with its own state
(box rotation R, centre t and, for body-model nodes, the 24 joint rotations) and its own
moment (the actor's clock). Actors inserted from another run are drawn the same way by
*that run's* node (its Gaussians, appearance and deformation). Nodes without actors
(background, sky) render as recorded. A :class:`Simulation` is the runtime's
:class:`~omnire.api.ActorEdits`: ``Reconstruction.drawn`` asks it which actors it draws
itself and ``Reconstruction.render`` renders the result, so an empty scenario renders
exactly what ``Reconstruction.render`` does without edits.

Shapes: box poses R (3, 3) / t (3,) per actor as torch float32 on the model's device; body
rotations (24, 3, 3), SMPL joint order, root = orientation relative to the box.
"""
from __future__ import annotations

import dataclasses
import math
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from omnire.api import (
    MAX_FPS,
    MAX_MOTION_FRAMES,
    ActorNode,
    ActorState,
    Camera,
    Reconstruction,
    SceneTime,
    UserError,
    axis_angle_to_rotmat,
    bracket,
    check_npz_rows,
    interpolate_poses,
    interpolate_rotations,
    rot_z,
)
from omnire_body.motion import gait_phase, gait_pose
from omnire_body.rest import BODY_TO_BOX
from omnire_sim.edits import ActorEdit, Clock, Insertion, Motion, Placement, Scenario, Trajectory, Where

_EPS_T = 1e-9


def has_body(node) -> bool:
    """True for actor nodes with a skinned body model (pedestrians: SMPL node type)."""
    return hasattr(node, "rotations_at") and hasattr(node, "joints")


def describe_missing(recon: Reconstruction, track: str, run: str = "this run") -> str:
    """Why ``track`` is not an editable actor of ``recon`` (for error messages)."""
    in_scene = any(t.track_id == track for t in recon.scene.tracks)
    if in_scene:
        return (f"track {track!r} is in the scene but {run} draws it as part of the background (no actor node took "
                "it: too small, never seen by a camera, or its node type is disabled); it cannot be edited")
    actors = [(t, name) for name, node in recon.actor_nodes().items() for t in node.track_ids]
    sample = ", ".join(f"{t} ({n})" for t, n in actors[:6]) + (" ..." if len(actors) > 6 else "")
    return f"no track {track!r} in {run} ({len(actors)} actors: {sample or 'none'})"


def seconds_of(recon: Reconstruction) -> np.ndarray:
    ts = np.asarray(recon.scene.frame_timestamps, dtype=np.float64)
    return ts - ts[0]


def path_headings(xy: np.ndarray, fallback: float) -> np.ndarray:
    """(K,) headings (radians) along a polyline (K, 2): at each point the bisector of the
    neighbouring moving segments; points on a standing stretch take the nearest moving
    segment's direction; ``fallback`` when nothing moves."""
    K = len(xy)
    seg = np.diff(xy, axis=0)
    moving = np.linalg.norm(seg, axis=1) > 1e-6 if K > 1 else np.zeros(0, bool)
    units = np.zeros_like(seg)
    units[moving] = seg[moving] / np.linalg.norm(seg[moving], axis=1, keepdims=True)
    out = np.full(K, fallback, dtype=np.float64)
    if not moving.any():
        return out
    idx = np.flatnonzero(moving)
    for k in range(K):
        near = [s for s in (k - 1, k) if 0 <= s < K - 1 and moving[s]]
        if not near:  # standing: nearest moving segment
            near = [int(idx[np.argmin(np.abs(idx - k + 0.5))])]
        v = sum(units[s] for s in near)
        if np.linalg.norm(v) < 1e-6:  # a U-turn: face the outgoing segment
            v = units[near[-1]]
        out[k] = math.atan2(v[1], v[0])
    return out


@dataclasses.dataclass
class _PoseSource:
    """Where an actor's box is at actor time tau: a recorded track (``node``/``instance`` of
    ``recon``) or interpolated waypoints (times (K,), poses (K, 4, 4), cumulative path
    length (K,))."""

    recon: Optional[Reconstruction] = None
    node: Optional[ActorNode] = None
    instance: int = -1
    times: Optional[np.ndarray] = None
    poses: Optional[np.ndarray] = None
    arc: Optional[np.ndarray] = None
    hold: bool = True
    device: torch.device = torch.device("cpu")
    _frames_arc: Optional[tuple[np.ndarray, np.ndarray]] = None

    @property
    def recorded(self) -> bool:
        return self.times is None

    def state(self, tau: float, exact: Optional[SceneTime] = None):
        """(R (3, 3), t (3,), body (24, 3, 3) or None) torch, or None when absent.
        ``exact``: the SceneTime to use when tau is the scene moment itself."""
        if self.recorded:
            dur = float(seconds_of(self.recon)[-1])
            if tau < -_EPS_T or tau > dur + _EPS_T:
                return None
            st = self.node.state_at(exact if exact is not None else self.recon.time_since_start(tau))
            hit = torch.nonzero(st.ids == self.instance).flatten()
            if len(hit) == 0:
                return None
            k = int(hit[0])
            return st.R[k], st.t[k], (None if st.body is None else st.body[k])
        if not self.hold and (tau < self.times[0] - _EPS_T or tau > self.times[-1] + _EPS_T):
            return None
        P = interpolate_poses(self.times, self.poses, tau)[0]
        dev = self.device
        return (torch.as_tensor(P[:3, :3], dtype=torch.float32, device=dev),
                torch.as_tensor(P[:3, 3], dtype=torch.float32, device=dev), None)

    @torch.no_grad()
    def distance(self, tau: float) -> float:
        """Path length (m) covered by actor time ``tau``."""
        if not self.recorded:
            return float(np.interp(tau, self.times, self.arc))
        if self._frames_arc is None:
            frames, centres = [], []
            for f in range(self.recon.scene.num_frames):
                st = self.node.state_at(self.recon.scene.time_of_frame(f))
                hit = torch.nonzero(st.ids == self.instance).flatten()
                if len(hit):
                    frames.append(f)
                    centres.append(st.t[int(hit[0])].detach().cpu().double().numpy())
            centres = np.asarray(centres).reshape(-1, 3)
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1))])
            self._frames_arc = (np.asarray(frames, dtype=np.float64), arc)
        frames, arc = self._frames_arc
        if len(frames) == 0:
            return 0.0
        sec = seconds_of(self.recon)
        frame = float(np.interp(tau, sec, np.arange(len(sec))))
        return float(np.interp(frame, frames, arc))


@dataclasses.dataclass
class _BodySequence:
    """Body rotations (T, 23, 3, 3) sampled at ``fps``, played from time 0."""

    rotations: np.ndarray
    fps: float
    loop: bool

    def at(self, u: float) -> np.ndarray:
        T = len(self.rotations)
        x = u * self.fps
        if self.loop:
            x = x % T
            R = np.concatenate([self.rotations, self.rotations[:1]])  # wrap: last -> first
            known = np.arange(T + 1, dtype=np.float64)
        else:
            R, known = self.rotations, np.arange(T, dtype=np.float64)
        i0, i1, w = bracket(known, x)
        return interpolate_rotations(R, i0, i1, w)[0]


def load_body_sequence(path: Path, motion: Motion, where: Where) -> _BodySequence:
    """An SMPL body-pose sequence from an npz (see :class:`~omnire_sim.edits.Motion`)."""
    if not path.is_file():
        raise where.error("motion", f"{path}: body-pose sequence file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            check_npz_rows(data, MAX_MOTION_FRAMES, str(path), "use a shorter sequence")
            arrays = {k: np.asarray(data[k]) for k in data.files}
    except UserError as exc:
        raise where.error("motion", str(exc)) from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise where.error("motion", f"{path}: cannot read the npz ({exc})") from None
    if "body_pose" in arrays:
        aa = arrays["body_pose"].astype(np.float64)
        if aa.ndim == 2 and aa.shape[1] == 69:
            aa = aa.reshape(-1, 23, 3)
        if aa.ndim != 3 or aa.shape[1:] != (23, 3):
            raise where.error("motion", f"{path}: 'body_pose' has shape {arrays['body_pose'].shape}; expected "
                                        "(T, 23, 3) "
                                        "or (T, 69) axis-angles")
    elif "poses" in arrays:
        poses = arrays["poses"].astype(np.float64)
        if poses.ndim != 2 or poses.shape[1] < 72:
            raise where.error("motion", f"{path}: 'poses' has shape {poses.shape}; expected (T, >= 72) SMPL "
                                        "axis-angles")
        aa = poses[:, 3:72].reshape(-1, 23, 3)
    else:
        raise where.error("motion", f"{path}: no 'body_pose' (T, 23, 3) or 'poses' (T, 72+) array; "
                                    f"found {sorted(arrays)}")
    if len(aa) == 0 or not np.isfinite(aa).all():
        raise where.error("motion", f"{path}: empty or non-finite body poses")
    fps = motion.fps
    for key in ("fps", "mocap_framerate"):
        if fps is None and key in arrays:
            value = arrays[key]
            if value.size != 1 or value.dtype.kind not in "iuf":
                raise where.error("motion", f"{path}: '{key}' must be one number (frames per second), got a "
                                            f"{value.dtype} array of shape {value.shape}")
            fps = float(value.reshape(()))
    fps = 30.0 if fps is None else fps
    if not (math.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise where.error("motion", f"{path}: frame rate {fps} must be in (0, {MAX_FPS:g}]")
    return _BodySequence(axis_angle_to_rotmat(aa), fps, motion.loop)


@dataclasses.dataclass
class SimActor:
    """One edited or inserted actor, resolved: which node draws it (``node`` of ``owner``,
    instance ``instance``), where its box comes from (``pose``), its clock, placement and
    body motion. ``removed`` actors are not drawn."""

    key: str
    where: Where
    node_name: str
    node: ActorNode
    owner: Reconstruction
    instance: int
    pose: Optional[_PoseSource] = None
    clock: Clock = Clock()
    origin: float = 0.0
    placement: Placement = Placement()
    z_shift: float = 0.0
    motion: Optional[str] = None  # None (no body) | "recorded" | "gait" | "sequence"
    gait: Optional[Motion] = None
    sequence: Optional[_BodySequence] = None
    new_root: bool = False
    source_time: Optional[float] = None
    removed: bool = False
    inserted: bool = False

    def tau(self, t: float) -> float:
        """Actor time at scene time ``t`` (seconds since the first frame)."""
        return t if self.clock.identity else self.clock(t, self.origin)

    @torch.no_grad()
    def state(self, t: float, scene_time: Optional[SceneTime] = None) -> Optional[tuple[ActorState, SceneTime]]:
        """The actor's state at scene time ``t`` (seconds since the first frame; the moment
        ``scene_time``) and the moment its node draws it at, or None when it is absent then
        (:class:`omnire.api.EditedActor`)."""
        tau = self.tau(t)
        exact = scene_time if (tau == t and self.pose.recorded and self.pose.recon is not None
                               and scene_time is not None and self.pose.recon is self.owner) else None
        got = self.pose.state(tau, exact)
        if got is None:
            return None
        R, tr, body = got
        dev = self.owner.device
        R, tr = R.to(dev), tr.to(dev)
        p = self.placement
        if not p.identity or self.z_shift:
            Ry = torch.as_tensor(rot_z(np.array(math.radians(p.yaw))), dtype=R.dtype, device=dev)
            off = torch.as_tensor(p.offset, dtype=R.dtype, device=dev)
            tr = tr + R @ off + torch.as_tensor(p.offset_world, dtype=R.dtype, device=dev)
            tr = tr + torch.tensor([0.0, 0.0, self.z_shift], dtype=R.dtype, device=dev)
            R = R @ Ry
        own_time = self.own_moment(tau)
        body_out = None
        if self.motion is not None:
            body_out = self.body(tau, t, body, own_time)
        ids = torch.tensor([self.instance], dtype=torch.long, device=dev)
        return ActorState(ids, R[None], tr[None], None if body_out is None else body_out[None]), own_time

    def own_moment(self, tau: float) -> SceneTime:
        """The moment of the owning run the node draws at (time-dependent appearance)."""
        if self.inserted:
            base = self.source_time if self.source_time is not None else 0.0
            return self.owner.time_since_start(base + tau - self.origin)
        return self.owner.time_since_start(tau)

    def body(self, tau: float, t: float, recorded: Optional[torch.Tensor], own: SceneTime) -> torch.Tensor:
        """(24, 3, 3) joint rotations (root relative to the box) at actor time ``tau``
        (scene time ``t``); ``recorded``: the rotations read with the box pose, if any."""
        dev = self.owner.device
        canon = torch.as_tensor(BODY_TO_BOX, dtype=torch.float32, device=dev)
        if self.motion == "recorded":
            if recorded is not None and self.pose.recorded and self.pose.node is self.node:
                return recorded  # its own recorded track: exactly the recorded body
            ids = torch.tensor([self.instance], dtype=torch.long, device=dev)
            rot = self.node.rotations_at(ids, own)[0]
            if self.new_root:  # upright, facing along the new path
                rot = torch.cat([canon[None].to(rot), rot[1:]], 0)
            return rot
        root = canon if (self.new_root or recorded is None) else recorded[0]
        if self.motion == "gait":
            g = self.gait
            h = 0.05  # s: speed from the path length around tau
            speed = abs(self.pose.distance(tau + h) - self.pose.distance(tau - h)) / (2 * h) * self.clock_rate(t)
            amp = min(1.0, speed / g.full_stride_speed)
            joints = gait_pose(gait_phase(np.array([self.pose.distance(tau)]), g.cycle), amp)[0]
        else:
            joints = self.sequence.at(max(0.0, tau - self.origin))
        joints = torch.as_tensor(joints, dtype=torch.float32, device=dev)
        return torch.cat([root[None].to(joints), joints], 0)

    def clock_rate(self, t: float) -> float:
        return 1.0 if self.clock.identity else self.clock.rate(t)


class Simulation:
    """A reconstructed scene with a scenario's edits applied; renders any camera at any
    moment (:meth:`render`). ``assets``: runs already loaded for insertions, by resolved
    path (others are loaded with ``plugins``). It is the runtime's
    :class:`~omnire.api.ActorEdits` (:meth:`edited`, :meth:`inserted`): what it draws is
    ``recon.drawn(time, sim)``.

    Example::

        sim = Simulation(recon, load_scenario(Path("scenario.toml")), plugins)
        image = sim.render(recon.camera(view), recon.time(view.frame)).rgb   # (H, W, 3)
    """

    def __init__(self, recon: Reconstruction, scenario: Scenario, plugins=None,
                 assets: Optional[dict[Path, Reconstruction]] = None) -> None:
        self.recon = recon
        self.scenario = scenario
        self.plugins = plugins
        self.assets: dict[Path, Reconstruction] = dict(assets or {})
        self.duration = float(seconds_of(recon)[-1])
        self.actors: list[SimActor] = []
        self._by_node: dict[str, dict[int, SimActor]] = {}
        for edit in scenario.actors:
            self._add(self._resolve_edit(edit))
        for ins in scenario.inserts:
            for actor in self._resolve_insert(ins):
                self._add(actor)
        self.sh_degree = max([recon.sh_degree()] + [a.sh_degree() for a in self.assets.values()])

    def _add(self, actor: SimActor) -> None:
        self.actors.append(actor)
        if not actor.inserted:
            self._by_node.setdefault(actor.node_name, {})[actor.instance] = actor

    # ------------------------------------------------------------------ resolution
    def _check_time(self, where: Where, field: str, t: Optional[float]) -> None:
        if t is not None and not -_EPS_T <= t <= self.duration + _EPS_T:
            raise where.error(field, f"{t:.6g} s is outside the log (0 .. {self.duration:.6g} s since its first frame)")

    def _check_clock(self, clock: Clock, where: Where) -> None:
        for field in ("stop_at", "resume_at"):
            self._check_time(where, field, getattr(clock, field))

    def _waypoint_source(self, traj: Trajectory, where: Where, z_default, fallback_yaw: float,
                         device: torch.device) -> _PoseSource:
        """Box poses (K, 4, 4) at the waypoints: heading along the path unless given, z from
        the waypoint or ``z_default(t)`` (None: z is required)."""
        times = traj.times()
        for k, tk in enumerate(times):
            if not -_EPS_T <= tk <= self.duration + _EPS_T:
                raise where.error(f"trajectory[{k + 1}]", f"time {tk:.6g} s is outside the log (0 .. "
                                                          f"{self.duration:.6g} s since its first frame)")
        wps = traj.waypoints
        xy = np.array([[w.x, w.y] for w in wps], dtype=np.float64)
        heading = path_headings(xy, fallback_yaw)
        poses = np.tile(np.eye(4), (len(wps), 1, 1))
        for k, w in enumerate(wps):
            if w.z is not None:
                z = w.z
            else:
                z = None if z_default is None else z_default(float(times[k]))
                if z is None:
                    raise where.error(f"trajectory[{k + 1}]", "needs 'z' (the box-centre height in metres): this "
                                                              "actor has no recorded height in this scene")
            yaw = heading[k] if w.yaw is None else math.radians(w.yaw)
            poses[k, :3, :3] = rot_z(np.array(yaw))
            poses[k, :3, 3] = [w.x, w.y, z]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))])
        return _PoseSource(times=times, poses=poses, arc=arc, hold=traj.hold, device=device)

    @torch.no_grad()
    def _recorded_z_and_yaw(self, node: ActorNode, instance: int):
        """Recorded box height at the present frame nearest to a time, and a heading."""
        recon = self.recon
        frames, zs, yaws = [], [], []
        for f in range(recon.scene.num_frames):
            st = node.state_at(recon.scene.time_of_frame(f))
            hit = torch.nonzero(st.ids == instance).flatten()
            if len(hit):
                k = int(hit[0])
                frames.append(f)
                zs.append(float(st.t[k, 2]))
                yaws.append(math.atan2(float(st.R[k, 1, 0]), float(st.R[k, 0, 0])))
        sec = seconds_of(recon)

        def z_at(t: float) -> Optional[float]:
            if not frames:
                return None
            f = float(np.interp(t, sec, np.arange(len(sec))))
            return zs[int(np.argmin(np.abs(np.asarray(frames) - f)))]

        return z_at, (yaws[len(yaws) // 2] if yaws else 0.0)

    def _motion(self, motion: Optional[Motion], node, where: Where, moved_path: bool, node_name: str):
        """(motion kind or None, gait settings, body sequence)."""
        if not has_body(node):
            if motion is not None:
                raise where.error("motion", f"body motions apply to pedestrians with a body model; this actor is "
                                            f"drawn by the '{node_name}' node, which has none")
            return None, None, None
        if motion is None:
            motion = Motion("gait") if moved_path else Motion("recorded")
        if motion.kind == "sequence":
            return "sequence", None, load_body_sequence(self.scenario.resolve_path(motion.file), motion, where)
        return motion.kind, (motion if motion.kind == "gait" else None), None

    def _resolve_edit(self, edit: ActorEdit) -> SimActor:
        w = edit.where
        found = self.recon.find_actor(edit.track)
        if found is None:
            raise w.error("track", describe_missing(self.recon, edit.track))
        name, node, instance = found
        self._check_clock(edit.clock, w)
        actor = SimActor(edit.track, w, name, node, self.recon, instance, clock=edit.clock, placement=edit.placement,
                         removed=edit.remove)
        if edit.remove:
            actor.pose = _PoseSource(recon=self.recon, node=node, instance=instance, device=self.recon.device)
            return actor
        if edit.trajectory is not None:
            z_at, yaw = self._recorded_z_and_yaw(node, instance)
            actor.pose = self._waypoint_source(edit.trajectory, w, z_at, yaw, self.recon.device)
            actor.origin = float(actor.pose.times[0])
            actor.new_root = True
        else:
            actor.pose = _PoseSource(recon=self.recon, node=node, instance=instance, device=self.recon.device)
        actor.motion, actor.gait, actor.sequence = self._motion(edit.motion, node, w, edit.trajectory is not None, name)
        if edit.clock.stop_at is not None and actor.pose.recorded:
            tau = actor.tau(edit.clock.stop_at)
            if actor.pose.state(tau) is None:
                raise w.error("stop_at", f"track {edit.track!r} is not in the log at its time {tau:.6g} s (where "
                                         f"stop_at = {edit.clock.stop_at:.6g} s freezes it): it cannot stop there")
        return actor

    def _asset(self, ins: Insertion) -> Reconstruction:
        path = self.scenario.resolve_path(ins.run).resolve()
        if path in self.assets:
            return self.assets[path]
        if self.plugins is None:
            raise ins.where.error("run", f"{path}: not loaded (pass plugins to load asset runs)")
        try:
            recon = Reconstruction.from_run(path, self.plugins, device=str(self.recon.device))
        except UserError as exc:
            raise ins.where.error("run", f"cannot load the asset run: {exc}") from None
        except (OSError, ValueError, KeyError, RuntimeError) as exc:
            raise ins.where.error("run", f"{path}: unreadable asset run ({type(exc).__name__}: {exc})") from None
        self.assets[path] = recon
        return recon

    def _resolve_insert(self, ins: Insertion) -> list[SimActor]:
        w = ins.where
        asset = self._asset(ins)
        found = asset.find_actor(ins.track)
        if found is None:
            raise w.error("track", describe_missing(asset, ins.track, f"the asset run {ins.run}"))
        name, node, instance = found
        self._check_clock(ins.clock, w)
        asset_dur = float(seconds_of(asset)[-1])
        present = [f for f in range(asset.scene.num_frames) if bool(node.poses.present[instance, f])]
        if ins.source_time is not None:
            if not -_EPS_T <= ins.source_time <= asset_dur + _EPS_T:
                raise w.error("source_time", f"{ins.source_time:.6g} s is outside the asset run's log (0 .. "
                              f"{asset_dur:.6g} s)")
            source_time = ins.source_time
        else:
            source_time = float(seconds_of(asset)[present[len(present) // 2]]) if present else 0.0
        out = []
        actor = SimActor(ins.id, w, name, node, asset, instance, clock=ins.clock, placement=ins.placement,
                         source_time=source_time, inserted=True)
        if ins.replace is not None:
            target = self.recon.find_actor(ins.replace)
            if target is None:
                raise w.error("replace", describe_missing(self.recon, ins.replace))
            t_name, t_node, t_inst = target
            if t_inst in self._by_node.get(t_name, {}):
                raise w.error("replace", f"track {ins.replace!r} is already edited or replaced")
            actor.pose = _PoseSource(recon=self.recon, node=t_node, instance=t_inst, device=self.recon.device)
            # bottoms of the boxes aligned: the guest stands on the same ground
            h_guest = float(self._track_size(asset, ins.track)[2])
            h_target = float(self._track_size(self.recon, ins.replace)[2])
            actor.z_shift = 0.5 * (h_guest - h_target)
            actor.new_root = True
            removed = SimActor(ins.replace, w, t_name, t_node, self.recon, t_inst, removed=True,
                               pose=_PoseSource(recon=self.recon, node=t_node, instance=t_inst))
            out.append(removed)
            moved = True
        else:
            actor.pose = self._waypoint_source(ins.trajectory, w, None, 0.0, self.recon.device)
            actor.origin = float(actor.pose.times[0])
            actor.new_root = True
            moved = True
        actor.motion, actor.gait, actor.sequence = self._motion(ins.motion, node, w, moved, name)
        out.append(actor)
        return out

    @staticmethod
    def _track_size(recon: Reconstruction, track: str) -> np.ndarray:
        for t in recon.scene.tracks:
            if t.track_id == track:
                return np.asarray(t.size, dtype=np.float64)
        return np.zeros(3)

    # ------------------------------------------------------------------ the runtime's ActorEdits
    def edited(self, node_name: str) -> dict[int, SimActor]:
        """The scene actors of node ``node_name`` this simulation draws itself (edited or
        removed), by instance."""
        return self._by_node.get(node_name, {})

    def inserted(self) -> list[SimActor]:
        """The actors inserted from other runs, in scenario order."""
        return [a for a in self.actors if a.inserted]

    # ------------------------------------------------------------------ rendering
    def time(self, seconds: float) -> SceneTime:
        """The scene moment ``seconds`` after the log's first frame."""
        return self.recon.time_since_start(seconds)

    def actor(self, key: str) -> SimActor:
        for a in self.actors:
            if a.key == key:
                return a
        raise KeyError(key)

    def parts(self, time: SceneTime, camera: Optional[Camera] = None, only: Optional[set[str]] = None,
              hidden: frozenset[str] = frozenset()) -> list:
        """(name, NodeOutput or None) of everything drawn at scene moment ``time``
        (``Reconstruction.drawn`` with these edits). ``only``: draw only these actors (track
        ids / insert ids), no background or sky."""
        return self.recon.node_outputs(self.recon.drawn(time, self, only, hidden), camera, time)

    @torch.no_grad()
    def render(self, camera: Camera, time: SceneTime, only: Optional[set[str]] = None,
               hidden: frozenset[str] = frozenset()):
        """Render the edited scene at ``time`` through ``camera`` -> RenderResult (rgb, depth,
        alpha (H, W, C)). ``only``: just these actors (track / insert ids), without the
        background and the sky; ``hidden``: node names not drawn."""
        degree = None if not self.assets else self.sh_degree
        return self.recon.render(camera, time, hidden=hidden, sh_degree=degree, edits=self, only=only)

    @torch.no_grad()
    def render_cameras(self, cameras: list[Camera], time: SceneTime) -> list:
        """:meth:`render` through each of ``cameras`` (a rig) at ``time``, side by side where
        that is faster (``Reconstruction.render_cameras``): the same images."""
        degree = None if not self.assets else self.sh_degree
        return self.recon.render_cameras(cameras, time, sh_degree=degree, edits=self)
