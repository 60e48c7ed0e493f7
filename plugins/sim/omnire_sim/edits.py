"""The edit model: what a scenario changes in a reconstructed scene.

Plain data, checked for internal consistency here and against a scene and its runs when a
:class:`~omnire_sim.engine.Simulation` resolves it. Times are seconds since the first
loaded frame of the scene being edited (``t = 0`` there); positions are metres in its world
frame (z up); angles are degrees; box frames have x along the heading, y left, z up.

Per actor, by track id (:class:`ActorEdit`): remove; offset and rotate; follow a new
trajectory (:class:`Trajectory`: timed waypoints, interpolated); stop at a time, re-time by
a speed factor (:class:`Clock`); pedestrians a new body motion (:class:`Motion`: a gait
generated from their speed along the path, or an SMPL axis-angle sequence from a file).
:class:`Insertion` draws an actor of another run (its Gaussians and appearance) on a
trajectory, or in place of an actor of this scene (``replace``).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal, Optional

import numpy as np

from omnire.api import ConfigError

__all__ = [
    "ActorEdit", "CameraSpec", "Clock", "Insertion", "LaneShift", "Motion", "OutputSpec", "Placement", "Scenario",
    "ScenarioError", "Trajectory", "Waypoint",
]
"""The edit model (``omnire_sim`` re-exports it); ``Where`` (a source location) is internal."""


class ScenarioError(ConfigError):
    """A scenario is malformed or does not fit the scene; the message names the file, the
    line and the field."""


@dataclasses.dataclass(frozen=True)
class Where:
    """Where an item was written (for error messages): the scenario file, the table (e.g.
    ``[[actor]] #2``) and the line of each of its fields."""

    source: str = "<python>"
    table: str = ""
    line: Optional[int] = None
    field_lines: tuple[tuple[str, int], ...] = ()

    def of(self, field: str = "") -> str:
        """``scenario.toml line 12, [[actor]] #2, field 'trajectory'``."""
        lines = dict(self.field_lines)
        line = lines.get(field.split(".")[0].split("[")[0], self.line) if field else self.line
        parts = [self.source + (f" line {line}" if line else "")]
        if self.table:
            parts.append(self.table)
        if field:
            parts.append(f"field '{field}'")
        return ", ".join(parts)

    def error(self, field: str, message: str) -> ScenarioError:
        return ScenarioError(f"{self.of(field)}: {message}")


@dataclasses.dataclass(frozen=True)
class Waypoint:
    """One point of a trajectory. ``t``: seconds (None when the trajectory derives times
    from ``speed``); ``z``: box-centre height (None: the actor's recorded height);
    ``yaw``: heading in degrees about world z (None: along the path)."""

    x: float
    y: float
    t: Optional[float] = None
    z: Optional[float] = None
    yaw: Optional[float] = None


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """Timed waypoints; poses between them are interpolated (SLERP + linear,
    :func:`omnire.interpolation.interpolate_poses`), the heading turns along the path unless
    waypoints give ``yaw``. Waypoints without times are walked at ``speed`` m/s starting at
    ``start``. ``hold``: the actor waits at the first / last waypoint before / after them
    (else it is drawn only between their times)."""

    waypoints: tuple[Waypoint, ...]
    speed: Optional[float] = None
    start: float = 0.0
    hold: bool = True

    def times(self) -> np.ndarray:
        """(K,) waypoint times."""
        wps = self.waypoints
        if all(w.t is not None for w in wps):
            return np.array([w.t for w in wps], dtype=np.float64)
        xy = np.array([[w.x, w.y] for w in wps], dtype=np.float64)
        dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        return self.start + dist / float(self.speed)

    def check(self, where: Where, field: str = "trajectory") -> None:
        wps = self.waypoints
        if len(wps) == 0:
            raise where.error(field, "needs at least one waypoint")
        timed = [w.t is not None for w in wps]
        if any(timed) and not all(timed):
            raise where.error(field, "give 't' for every waypoint or for none (then 'speed' m/s sets the times)")
        if not all(timed):
            if self.speed is None or not self.speed > 0:
                raise where.error(field, "waypoints without 't' need a walking/driving 'speed' > 0 (m/s)")
        vals = [v for w in wps for v in (w.x, w.y, w.t, w.z, w.yaw) if v is not None]
        if not np.all(np.isfinite(vals)):
            raise where.error(field, "non-finite waypoint value")
        t = self.times()
        if len(t) > 1 and not np.all(np.diff(t) > 0):
            k = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise where.error(field, f"waypoint times must increase (waypoint {k + 1} at {t[k + 1]:.6g} s comes "
                                     f"after {t[k]:.6g} s); consecutive waypoints must differ")


@dataclasses.dataclass(frozen=True)
class Clock:
    """How the actor's own time runs against scene time: ``speed`` times as fast (from
    t = 0, or from the first waypoint of a new trajectory); stopped from ``stop_at`` (after
    slowing down linearly over the ``brake`` seconds before it) until ``resume_at`` (then
    speeding up over ``brake`` seconds again)."""

    speed: float = 1.0
    stop_at: Optional[float] = None
    brake: float = 0.0
    resume_at: Optional[float] = None

    @property
    def identity(self) -> bool:
        return self.speed == 1.0 and self.stop_at is None

    def check(self, where: Where) -> None:
        if not np.isfinite(self.speed) or self.speed < 0:
            raise where.error("speed", f"{self.speed}: must be a finite factor >= 0")
        if self.brake < 0 or not np.isfinite(self.brake):
            raise where.error("brake", f"{self.brake}: must be >= 0 seconds")
        if self.resume_at is not None:
            if self.stop_at is None:
                raise where.error("resume_at", "needs 'stop_at'")
            if self.resume_at < self.stop_at:
                raise where.error("resume_at", f"{self.resume_at} s is before stop_at = {self.stop_at} s")
        if self.stop_at is not None and self.brake > 0 and self.stop_at - self.brake < -1e-9:
            raise where.error("brake", f"braking for {self.brake} s before stop_at = {self.stop_at} s starts before "
                                       "the log (t = 0)")

    def speed_profile(self) -> tuple[np.ndarray, np.ndarray]:
        """Breakpoints (B,) and speed factors (B,) of the piecewise-linear speed s(t); s is
        constant beyond the first and last breakpoint."""
        k = self.speed
        if self.stop_at is None:
            return np.array([0.0]), np.array([k])
        s0 = self.stop_at - self.brake
        ts, vs = [s0, self.stop_at], [k, 0.0]
        if self.resume_at is not None:
            ts += [self.resume_at, self.resume_at + self.brake]
            vs += [0.0, k]
        # equal breakpoints (brake = 0) make a step: keep both values, integrate exactly
        return np.array(ts), np.array(vs)

    def __call__(self, t: float, origin: float = 0.0) -> float:
        """The actor's time at scene time ``t``: origin + integral from origin to t of s."""
        ts, vs = self.speed_profile()
        return origin + _integrate_pwl(ts, vs, origin, t)

    def rate(self, t: float) -> float:
        """ds/dt: the speed factor at scene time ``t``."""
        ts, vs = self.speed_profile()
        if t <= ts[0]:
            return float(vs[0])
        if t >= ts[-1]:
            return float(vs[-1])
        i = int(np.searchsorted(ts, t, side="right")) - 1
        if ts[i + 1] == ts[i]:
            return float(vs[i + 1])
        w = (t - ts[i]) / (ts[i + 1] - ts[i])
        return float((1 - w) * vs[i] + w * vs[i + 1])


def _integrate_pwl(ts: np.ndarray, vs: np.ndarray, a: float, b: float) -> float:
    """Integral from a to b of the piecewise-linear function through (ts, vs), constant
    outside [ts[0], ts[-1]]; steps where consecutive breakpoints coincide."""
    if b < a:
        return -_integrate_pwl(ts, vs, b, a)
    knots = np.concatenate([[a], ts[(ts > a) & (ts < b)], [b]])
    total = 0.0
    for lo, hi in zip(knots[:-1], knots[1:]):
        if hi <= lo:
            continue
        mid = 0.5 * (lo + hi)  # the function is linear on [lo, hi]: midpoint rule is exact
        total += (hi - lo) * _pwl_value(ts, vs, mid)
    return total


def _pwl_value(ts: np.ndarray, vs: np.ndarray, t: float) -> float:
    if t <= ts[0]:
        return float(vs[0])
    if t >= ts[-1]:
        return float(vs[-1])
    i = int(np.searchsorted(ts, t, side="right")) - 1
    w = (t - ts[i]) / (ts[i + 1] - ts[i])
    return float((1 - w) * vs[i] + w * vs[i + 1])


@dataclasses.dataclass(frozen=True)
class Motion:
    """A pedestrian's body motion. ``recorded``: the reconstructed body poses (at the
    actor's time); ``gait``: a walking cycle whose phase follows the distance walked (one
    cycle per ``cycle`` metres; the stride fades out below ``full_stride_speed`` m/s, so a
    stopped walker stands); ``sequence``: SMPL body-pose axis-angles from ``file`` (npz:
    ``body_pose`` (T, 23, 3) or (T, 69), or AMASS-style ``poses`` (T, >= 72); ``fps`` or
    ``mocap_framerate``, else ``fps`` here), played from the start of the trajectory,
    looped when ``loop``. The root orientation always comes from the trajectory."""

    kind: Literal["recorded", "gait", "sequence"] = "gait"
    cycle: float = 1.3
    full_stride_speed: float = 0.8
    file: Optional[Path] = None
    fps: Optional[float] = None
    loop: bool = True

    def check(self, where: Where, field: str = "motion") -> None:
        if self.kind not in ("recorded", "gait", "sequence"):
            raise where.error(field, f"{self.kind!r}: expected 'recorded', 'gait' or a sequence file")
        if self.kind == "gait" and not (self.cycle > 0 and self.full_stride_speed > 0):
            raise where.error(field, "gait cycle and full_stride_speed must be > 0")
        if self.kind == "sequence" and self.file is None:
            raise where.error(field, "a body-pose sequence needs a file")
        if self.fps is not None and not self.fps > 0:
            raise where.error(field, f"fps {self.fps}: must be > 0")


@dataclasses.dataclass(frozen=True)
class Placement:
    """A rigid change applied after the trajectory: rotate ``yaw`` degrees about the box's
    up axis, move ``offset`` metres in the box frame (x forward, y left, z up) and
    ``offset_world`` metres in the world frame."""

    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_world: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0

    @property
    def identity(self) -> bool:
        return not any(self.offset) and not any(self.offset_world) and self.yaw == 0.0


def _check_movement(where: Where, trajectory: Optional[Trajectory], clock: Clock, motion: Optional[Motion]) -> None:
    """The checks an edited and an inserted actor share: its path, clock and body motion."""
    if trajectory is not None:
        trajectory.check(where)
    clock.check(where)
    if motion is not None:
        motion.check(where)


@dataclasses.dataclass(frozen=True)
class ActorEdit:
    """Changes to one actor of the scene (by track id). See the module docstring."""

    track: str
    remove: bool = False
    placement: Placement = Placement()
    trajectory: Optional[Trajectory] = None
    clock: Clock = Clock()
    motion: Optional[Motion] = None
    where: Where = Where()

    def check(self) -> None:
        w = self.where
        if not self.track:
            raise w.error("track", "empty track id")
        changes = (not self.placement.identity or self.trajectory is not None or not self.clock.identity
                   or self.motion is not None)
        if self.remove and changes:
            raise w.error("remove", "a removed actor cannot also be moved, re-timed or given a motion")
        _check_movement(w, self.trajectory, self.clock, self.motion)


@dataclasses.dataclass(frozen=True)
class Insertion:
    """An actor of another run drawn in this scene: ``track`` of the run at ``run``, on
    ``trajectory`` or in place of this scene's actor ``replace`` (which is removed; the
    guest follows its recorded poses, bottoms of the boxes aligned). ``source_time``:
    the moment (seconds in the source run's log) whose appearance is used (deformation,
    recorded body pose); default: the middle of the frames where the actor is present."""

    id: str
    run: Path
    track: str
    trajectory: Optional[Trajectory] = None
    replace: Optional[str] = None
    source_time: Optional[float] = None
    placement: Placement = Placement()
    clock: Clock = Clock()
    motion: Optional[Motion] = None
    where: Where = Where()

    def check(self) -> None:
        w = self.where
        if (self.trajectory is None) == (self.replace is None):
            raise w.error("trajectory", "an inserted actor needs exactly one of 'trajectory' or 'replace'")
        _check_movement(w, self.trajectory, self.clock, self.motion)


@dataclasses.dataclass(frozen=True)
class LaneShift:
    """Move the camera rig ``offset`` metres to its left (negative: right), ramped in
    between ``start`` and ``end`` seconds of the path clock."""

    offset: float
    start: float = 0.0
    end: float = 0.0
    where: Where = Where()


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """The camera path: ``recorded`` frames, ``interpolated`` at ``fps`` over ``start`` ..
    ``end`` seconds, or rig poses from ``file``; ``cameras`` (default: all); an image size;
    lane shifts; the scene shown at a fixed ``scene_time`` or running at ``scene_speed``
    while the cameras move (scene time decoupled from camera pose)."""

    path: Literal["recorded", "interpolated", "file"] = "recorded"
    fps: Optional[float] = None
    start: float = 0.0
    end: Optional[float] = None
    frames: Optional[tuple[int, ...]] = None
    cameras: tuple[str, ...] = ()
    file: Optional[Path] = None
    width: Optional[int] = None
    height: Optional[int] = None
    scene_time: Optional[float] = None
    scene_speed: Optional[float] = None
    lane_shifts: tuple[LaneShift, ...] = ()
    where: Where = Where()


@dataclasses.dataclass(frozen=True)
class OutputSpec:
    """What is written: PNG ``frames`` per camera, an MP4 per camera (``video`` at ``fps``,
    default the path's rate; x264 ``crf``), optional ``depth`` (16-bit PNG, millimetres)
    and ``alpha`` (8-bit PNG)."""

    frames: bool = True
    video: bool = True
    fps: Optional[float] = None
    crf: int = 18
    depth: bool = False
    alpha: bool = False


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Everything a simulation changes. ``base_dir``: where relative paths (asset runs,
    motion and camera files) are resolved (the scenario file's directory)."""

    actors: tuple[ActorEdit, ...] = ()
    inserts: tuple[Insertion, ...] = ()
    camera: CameraSpec = CameraSpec()
    output: OutputSpec = OutputSpec()
    base_dir: Path = Path(".")
    source: str = "<python>"

    def check(self) -> "Scenario":
        seen: dict[str, Where] = {}
        for edit in self.actors:
            edit.check()
            if edit.track in seen:
                raise edit.where.error("track", f"track {edit.track!r} is edited twice "
                                                f"(first at {seen[edit.track].of()})")
            seen[edit.track] = edit.where
        ids: dict[str, Where] = {}
        for ins in self.inserts:
            ins.check()
            if ins.id in ids:
                raise ins.where.error("id", f"insert id {ins.id!r} is used twice")
            ids[ins.id] = ins.where
            if ins.replace is not None and ins.replace in seen:
                raise ins.where.error("replace", f"track {ins.replace!r} is replaced here and edited at "
                                                 f"{seen[ins.replace].of()}; edit one or the other")
        return self

    def resolve_path(self, p: Path) -> Path:
        p = Path(p).expanduser()
        return p if p.is_absolute() else (self.base_dir / p)
