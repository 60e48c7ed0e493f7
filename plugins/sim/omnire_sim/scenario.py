"""Scenario files (TOML, read by the core reader omnire/io/documents.py) -> :class:`Scenario`.

Every value is checked for its type and range; an error names the file, the line, the table
(``[[actor]] #2``) and the field. docs/simulation.md describes the format; in short::

    [camera]                       # the camera path (default: recorded frames, all cameras)
    path = "interpolated"          # "recorded" | "interpolated" | "file"
    fps = 20
    cameras = ["front_camera"]
    [[camera.lane_shift]]          # the rig 2 m to the left, ramped in over 1 s
    offset = 2.0
    start = 1.0
    end = 2.0

    [[actor]]                      # a recorded actor, by track id
    track = "0d238564-..."
    remove = true

    [[actor]]
    track = "17cc789c-..."
    stop_at = 2.5                  # stationary from 2.5 s, after braking for 1.5 s
    brake = 1.5

    [[actor]]                      # a pedestrian crossing on a new path, walking
    track = "dede81a6-..."
    trajectory = [{t = 0.5, x = 30.0, y = 8.0}, {t = 6.0, x = 30.0, y = -8.0}]
    motion = "gait"

    [[insert]]                     # an actor of another run
    id = "guest"
    run = "../other-run"
    track = "a1b2..."
    trajectory = [[0.0, 12.0, -3.5, 0.8], [4.0, 40.0, -3.5, 0.8]]   # [t, x, y(, z)]
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from omnire.api import (
    MAX_FPS,
    MAX_IMAGE_SIDE,
    ConfigError,
    TomlDocument,
    check_offset,
    check_positions,
    parse_toml,
    read_text,
)
from omnire_sim.edits import (
    ActorEdit,
    CameraSpec,
    Clock,
    Insertion,
    LaneShift,
    Motion,
    OutputSpec,
    Placement,
    Scenario,
    ScenarioError,
    Trajectory,
    Waypoint,
    Where,
)

class _Lines:
    """Where each table and key of a scenario was written (from the core TOML reader)."""

    def __init__(self, doc: TomlDocument) -> None:
        self.doc = doc

    def where(self, source: str, name: str, index: int, label: str) -> Where:
        return Where(source, label, self.doc.line(name, index), tuple(self.doc.key_lines(name, index).items()))


# ---------------------------------------------------------------------- field readers
class _Table:
    """A TOML table with typed, located field access; unknown keys are refused."""

    def __init__(self, data: dict, where: Where, known: set[str]) -> None:
        self.data, self.where = data, where
        unknown = sorted(set(data) - known)
        if unknown:
            raise where.error(unknown[0], f"unknown field; expected one of {sorted(known)}")

    def has(self, key: str) -> bool:
        return key in self.data

    def get(self, key: str, kind: str, default: Any = None,
            check: Optional[Callable[[Any], Optional[str]]] = None) -> Any:
        if key not in self.data:
            return default
        value = _convert(self.data[key], kind, self.where, key)
        if check is not None:
            problem = check(value)
            if problem:
                raise self.where.error(key, f"{_show(self.data[key])}: {problem}")
        return value

    def require(self, key: str, kind: str, check=None) -> Any:
        if key not in self.data:
            raise self.where.error(key, f"missing (expected {kind})")
        return self.get(key, kind, check=check)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _convert(value: Any, kind: str, where: Where, key: str) -> Any:
    def bad(expected: str) -> ScenarioError:
        return where.error(key, f"{_show(value)}: expected {expected}")

    if kind == "bool":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if kind == "str":
        if not isinstance(value, str) or not value:
            raise bad("a non-empty string")
        return value
    if kind in ("number", "seconds"):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad("a finite number" + (" of seconds" if kind == "seconds" else ""))
        return float(value)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if kind == "vec3":
        numbers = isinstance(value, list) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
        if not numbers or len(value) != 3:
            raise bad("3 finite numbers [x, y, z]")
        return tuple(float(v) for v in value)
    if kind == "str_list":
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise bad("a list of names")
        return tuple(value)
    if kind == "int_list":
        if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            raise bad("a list of integers")
        return tuple(value)
    raise AssertionError(kind)


def _positive(v: float) -> Optional[str]:
    return None if v > 0 else "must be > 0"


def _non_negative(v: float) -> Optional[str]:
    return None if v >= 0 else "must be >= 0"


def _fps(v: float) -> Optional[str]:
    return None if 0 < v <= MAX_FPS else f"must be a frame rate in (0, {MAX_FPS:g}]"


def _side(v: int) -> Optional[str]:
    return None if 1 <= v <= MAX_IMAGE_SIDE else f"must be 1..{MAX_IMAGE_SIDE} pixels"


# ---------------------------------------------------------------------- sections
_MOVE_KEYS = {"offset", "offset_world", "yaw", "trajectory", "path_speed", "path_start", "hold", "speed", "stop_at",
              "brake", "resume_at", "motion", "gait_cycle", "motion_fps", "motion_loop"}


def _waypoints(value: Any, where: Where) -> tuple[Waypoint, ...]:
    if not isinstance(value, list) or not value:
        raise where.error("trajectory", f"{_show(value)}: expected a list of waypoints, each "
                                        "{t = .., x = .., y = .. (, z = .., yaw = ..)} or [t, x, y(, z)]")
    out = []
    for k, wp in enumerate(value, start=1):
        field = f"trajectory[{k}]"
        if isinstance(wp, list):
            if len(wp) not in (3, 4) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in wp):
                raise where.error(field, f"{_show(wp)}: expected [t, x, y] or [t, x, y, z] (numbers)")
            out.append(Waypoint(x=float(wp[1]), y=float(wp[2]), t=float(wp[0]),
                                z=float(wp[3]) if len(wp) == 4 else None))
            continue
        if not isinstance(wp, dict):
            raise where.error(field, f"{_show(wp)}: expected {{t = .., x = .., y = ..}} or [t, x, y]")
        unknown = sorted(set(wp) - {"t", "x", "y", "z", "yaw"})
        if unknown:
            raise where.error(field, f"unknown key {unknown[0]!r}; expected t, x, y, z, yaw")
        vals = {}
        for key in ("t", "x", "y", "z", "yaw"):
            if key in wp:
                vals[key] = _convert(wp[key], "number", where, f"{field}.{key}")
        for key in ("x", "y"):
            if key not in vals:
                raise where.error(field, f"missing '{key}'")
        out.append(Waypoint(**vals))
    return tuple(out)


def _moves(t: _Table, base_dir: Path) -> tuple[Placement, Optional[Trajectory], Clock, Optional[Motion]]:
    w = t.where
    placement = Placement(t.get("offset", "vec3", (0.0, 0.0, 0.0)), t.get("offset_world", "vec3", (0.0, 0.0, 0.0)),
                          t.get("yaw", "number", 0.0))
    trajectory = None
    if t.has("trajectory"):
        trajectory = Trajectory(_waypoints(t.data["trajectory"], w), t.get("path_speed", "number", None, _positive),
                                t.get("path_start", "seconds", 0.0), t.get("hold", "bool", True))
    else:
        for key in ("path_speed", "path_start", "hold"):
            if t.has(key):
                raise w.error(key, "only applies with a 'trajectory'")
    clock = Clock(t.get("speed", "number", 1.0, _non_negative), t.get("stop_at", "seconds"),
                  t.get("brake", "seconds", 0.0, _non_negative), t.get("resume_at", "seconds"))
    motion = None
    if t.has("motion"):
        name = t.require("motion", "str")
        extra = dict(cycle=t.get("gait_cycle", "number", 1.3, _positive),
                     fps=t.get("motion_fps", "number", None, _fps), loop=t.get("motion_loop", "bool", True))
        if name in ("gait", "recorded"):
            motion = Motion(name, **extra)
        else:
            motion = Motion("sequence", file=Path(name), **extra)
    else:
        for key in ("gait_cycle", "motion_fps", "motion_loop"):
            if t.has(key):
                raise w.error(key, "only applies with a 'motion'")
    return placement, trajectory, clock, motion


def _actor(data: Any, where: Where, base_dir: Path) -> ActorEdit:
    if not isinstance(data, dict):
        raise where.error("", "expected a table")
    t = _Table(data, where, {"track", "remove"} | _MOVE_KEYS)
    placement, trajectory, clock, motion = _moves(t, base_dir)
    return ActorEdit(t.require("track", "str"), t.get("remove", "bool", False), placement, trajectory, clock, motion,
                     where)


def _insert(data: Any, where: Where, base_dir: Path) -> Insertion:
    if not isinstance(data, dict):
        raise where.error("", "expected a table")
    t = _Table(data, where, {"id", "run", "track", "replace", "source_time"} | _MOVE_KEYS)
    placement, trajectory, clock, motion = _moves(t, base_dir)
    return Insertion(t.require("id", "str"), Path(t.require("run", "str")), t.require("track", "str"), trajectory,
                     t.get("replace", "str"), t.get("source_time", "seconds"), placement, clock, motion, where)


def _camera(data: Any, lines: _Lines, source: str) -> CameraSpec:
    where = lines.where(source, "camera", 0, "[camera]")
    if not isinstance(data, dict):
        raise where.error("", "expected a table")
    t = _Table(data, where, {"path", "fps", "start", "end", "frames", "cameras", "file", "width", "height",
                             "scene_time", "scene_speed", "lane_shift"})
    path = t.get("path", "str", "recorded")
    if path not in ("recorded", "interpolated", "file"):
        raise where.error("path", f"{path!r}: expected 'recorded', 'interpolated' or 'file'")
    if path == "interpolated" and not t.has("fps"):
        raise where.error("fps", "an interpolated path needs 'fps'")
    if path == "file" and not t.has("file"):
        raise where.error("file", "path = 'file' needs 'file' (an npz or JSON of rig poses)")
    if path != "recorded" and t.has("frames"):
        raise where.error("frames", "only applies to the recorded path")
    if path == "recorded" and (t.has("start") or t.has("end")):
        raise where.error("start" if t.has("start") else "end", "the recorded path takes 'frames', not a time window")
    width, height = t.get("width", "int", None, _side), t.get("height", "int", None, _side)
    if (width is None) != (height is None):
        raise where.error("width" if width is None else "height", "give both 'width' and 'height'")
    if t.has("scene_time") and t.has("scene_speed"):
        raise where.error("scene_speed", "give 'scene_time' (frozen) or 'scene_speed', not both")
    shifts = []
    raw = data.get("lane_shift", [])
    if isinstance(raw, dict):
        raw = [raw]
    if not isinstance(raw, list):
        raise where.error("lane_shift", "expected [[camera.lane_shift]] tables")
    for i, item in enumerate(raw):
        sw = lines.where(source, "camera.lane_shift", i, f"[[camera.lane_shift]] #{i + 1}")
        if sw.line is None:  # written inline: point at the camera table's key
            sw = Where(source, f"[camera] lane_shift #{i + 1}", where.line, where.field_lines)
        if not isinstance(item, dict):
            raise sw.error("", "expected a table {offset, start, end}")
        st = _Table(item, sw, {"offset", "start", "end"})
        offset = st.require("offset", "number")
        start = st.get("start", "seconds", 0.0)
        end = st.get("end", "seconds", start)
        if end < start:
            raise sw.error("end", f"{end} s is before start = {start} s")
        shifts.append(LaneShift(offset, start, end, sw))
    file = t.get("file", "str")
    return CameraSpec(path, t.get("fps", "number", None, _fps), t.get("start", "seconds", 0.0),
                      t.get("end", "seconds"), t.get("frames", "int_list"), t.get("cameras", "str_list", ()),
                      Path(file) if file else None, width, height, t.get("scene_time", "seconds"),
                      t.get("scene_speed", "number", None, _non_negative), tuple(shifts), where)


def _output(data: Any, lines: _Lines, source: str) -> OutputSpec:
    where = lines.where(source, "output", 0, "[output]")
    if not isinstance(data, dict):
        raise where.error("", "expected a table")
    t = _Table(data, where, {"frames", "video", "fps", "crf", "depth", "alpha"})
    crf = t.get("crf", "int", 18, lambda v: None if 0 <= v <= 51 else "x264 crf must be in 0..51")
    return OutputSpec(t.get("frames", "bool", True), t.get("video", "bool", True),
                      t.get("fps", "number", None, _fps), crf, t.get("depth", "bool", False),
                      t.get("alpha", "bool", False))


def parse_scenario(text: str, source: str = "<scenario>", base_dir: Path = Path(".")) -> Scenario:
    """Parse and check a scenario written as TOML ``text`` (``source`` names it in errors;
    relative paths in it are resolved against ``base_dir``)."""
    doc = parse_toml(text, source, ScenarioError)
    data, lines = doc.data, _Lines(doc)
    top = _Table(data, lines.where(source, "", 0, ""), {"camera", "output", "actor", "insert"})
    del top
    actors, inserts = [], []
    for key, reader, out in (("actor", _actor, actors), ("insert", _insert, inserts)):
        items = data.get(key, [])
        if not isinstance(items, list):
            w = lines.where(source, "", 0, "")
            raise w.error(key, f"expected [[{key}]] tables")
        for i, item in enumerate(items):
            out.append(reader(item, lines.where(source, key, i, f"[[{key}]] #{i + 1}"), base_dir))
    camera = _camera(data["camera"], lines, source) if "camera" in data else CameraSpec()
    output = _output(data["output"], lines, source) if "output" in data else OutputSpec()
    return Scenario(tuple(actors), tuple(inserts), camera, output, base_dir, source).check()


def load_scenario(path: Path) -> Scenario:
    """Read a scenario file (see the module docstring); relative paths inside it are taken
    relative to its directory."""
    path = Path(path)
    return parse_scenario(read_text(path, "scenario file", ScenarioError), str(path), path.parent.resolve())


def check_against_scene(scenario: Scenario, scene) -> None:
    """Refuse positions and offsets that leave the scene: trajectory waypoints outside the
    scene's extent plus :data:`omnire.limits.POSITION_MARGIN_M`, placement offsets and lane
    shifts longer than that extent plus the margin. Run before any rendering; the error
    names the file, line, table and field."""
    for item in (*scenario.actors, *scenario.inserts):
        w = item.where
        try:
            check_offset(item.placement.offset, scene, w.of("offset"))
            check_offset(item.placement.offset_world, scene, w.of("offset_world"))
            if item.trajectory is not None:
                for k, wp in enumerate(item.trajectory.waypoints, start=1):
                    point = [wp.x, wp.y] + ([wp.z] if wp.z is not None else [])
                    check_positions(np.array([point]), scene, w.of(f"trajectory[{k}]"))
        except ConfigError as exc:
            raise ScenarioError(str(exc)) from None
    for shift in scenario.camera.lane_shifts:
        try:
            check_offset(shift.offset, scene, shift.where.of("offset"))
        except ConfigError as exc:
            raise ScenarioError(str(exc)) from None
