"""Camera paths: where each rendered camera is at each output frame, and which moment of the
scene that frame shows.

A :class:`CameraPath` holds, for T output frames and C cameras, camera-to-world poses, the
*path clock* (seconds since the log's first frame, on which edits such as a lane shift are
timed), the scene moment shown (a fractional frame index, so scene time can be decoupled
from camera pose: frozen, slowed down, ...) and the rig pose (ego frame: x forward, y left,
z up) the cameras are mounted on. Paths come from:

- :func:`recorded_path`: the recorded cameras at recorded frames;
- :func:`interpolated_path`: any frame rate over any time window, camera poses SLERPed /
  linearly interpolated between the recorded ones (:mod:`omnire.interpolation`); at the
  recorded timestamps it returns the recorded poses exactly;
- :func:`file_path`: rig poses from a file (npz or JSON), cameras mounted as recorded;

and are edited by :meth:`CameraPath.lane_shifted` (a lateral offset ramped in over a time
window), :meth:`CameraPath.with_scene_time` / :meth:`CameraPath.with_scene_speed`,
:meth:`CameraPath.resized` and :meth:`CameraPath.select` (any subset of cameras). Times are
seconds since the first loaded frame (``t = 0`` there). Arrays are numpy float64.
"""
from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from omnire.camera import Camera
from omnire.data.scene import SceneData, SceneTime
from omnire.errors import ConfigError, MissingFileError
from omnire.interpolation import bracket, interpolate_poses
from omnire.io.documents import load_json
from omnire.limits import (
    DEFAULT_FRAME_CAP,
    check_fps,
    check_frame_count,
    check_image_size,
    check_npz_rows,
    check_positions,
    file_size_cap,
)


@dataclasses.dataclass(frozen=True)
class CameraPath:
    """T output frames of C cameras. See the module docstring.

    Attributes:
        names: (C,) camera names (as the scene calls them).
        intrinsics: (C, 3, 3) pinhole K in pixels at ``sizes``.
        sizes: (C,) (width, height) per camera.
        cam_to_world: (C, T, 4, 4) OpenCV camera-to-world per output frame.
        seconds: (T,) path clock: seconds since the log's first frame.
        scene_frames: (T,) the scene moment each frame shows, as a fractional frame index.
        rig_to_world: (T, 4, 4) the rig (ego) pose per frame: x forward, y left, z up.
        fps: output frame rate (for videos).
    """

    names: tuple[str, ...]
    intrinsics: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    cam_to_world: np.ndarray
    seconds: np.ndarray
    scene_frames: np.ndarray
    rig_to_world: np.ndarray
    fps: float

    def __post_init__(self) -> None:
        C, T = len(self.names), len(self.seconds)
        if self.cam_to_world.shape != (C, T, 4, 4) or self.intrinsics.shape != (C, 3, 3):
            raise ValueError(f"CameraPath: cam_to_world {self.cam_to_world.shape} / intrinsics "
                             f"{self.intrinsics.shape} do not match {C} cameras x {T} frames")
        if self.scene_frames.shape != (T,) or self.rig_to_world.shape != (T, 4, 4) or len(self.sizes) != C:
            raise ValueError("CameraPath: scene_frames (T,), rig_to_world (T, 4, 4) and sizes (C,) must match")

    def __len__(self) -> int:
        return len(self.seconds)

    def time(self, scene: SceneData, i: int) -> SceneTime:
        """The scene moment output frame ``i`` shows."""
        return scene.time_of_frame(float(self.scene_frames[i]))

    def camera(self, c: int, i: int, device: torch.device | str = "cpu") -> Camera:
        """Camera ``c`` (index into ``names``) at output frame ``i``."""
        w, h = self.sizes[c]
        return Camera.from_numpy(self.intrinsics[c], self.cam_to_world[c, i], w, h, self.names[c], device)

    # ------------------------------------------------------------------ edits
    def select(self, names: Sequence[str]) -> "CameraPath":
        """Only the cameras ``names`` (in that order)."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise ConfigError(f"cameras {missing}: not in this path; cameras: {list(self.names)}")
        idx = [self.names.index(n) for n in names]
        return dataclasses.replace(self, names=tuple(names), intrinsics=self.intrinsics[idx],
                                   sizes=tuple(self.sizes[i] for i in idx), cam_to_world=self.cam_to_world[idx])

    def resized(self, width: int, height: int) -> "CameraPath":
        """Every camera rendering ``width`` x ``height`` pixels (K scaled per axis)."""
        check_image_size(width, height, "image size")
        K = self.intrinsics.copy()
        for c, (w, h) in enumerate(self.sizes):
            K[c, 0] *= width / w
            K[c, 1] *= height / h
        return dataclasses.replace(self, intrinsics=K, sizes=tuple((int(width), int(height)) for _ in self.names))

    def lane_shifted(self, offset: float, start: float, end: float) -> "CameraPath":
        """The whole rig moved ``offset`` metres sideways (positive = to the rig's left),
        ramped in smoothly (smoothstep) between path times ``start`` and ``end`` seconds and
        held after ``end``; ``start == end`` shifts at once. The direction is the rig's
        left axis made horizontal (world z up), so the cameras keep their height."""
        if end < start:
            raise ConfigError(f"lane shift window: end {end} s is before start {start} s")
        if end > start:
            s = np.clip((self.seconds - start) / (end - start), 0.0, 1.0)
            ramp = s * s * (3.0 - 2.0 * s)
        else:
            ramp = (self.seconds >= start).astype(np.float64)
        left = self.rig_to_world[:, :3, 1].copy()
        left[:, 2] = 0.0
        norm = np.linalg.norm(left, axis=1, keepdims=True)
        if np.any(norm < 1e-6):
            raise ConfigError("lane shift: the rig's left axis is vertical at some frame; no horizontal direction")
        move = (offset * ramp)[:, None] * left / norm  # (T, 3)
        c2w = self.cam_to_world.copy()
        c2w[:, :, :3, 3] += move[None]
        rig = self.rig_to_world.copy()
        rig[:, :3, 3] += move
        return dataclasses.replace(self, cam_to_world=c2w, rig_to_world=rig)

    def with_scene_time(self, scene: SceneData, seconds: "float | np.ndarray") -> "CameraPath":
        """Show the scene at ``seconds`` (scalar: frozen there; or (T,) per frame) while the
        cameras keep their poses: scene time decoupled from camera pose."""
        sec = np.broadcast_to(np.asarray(seconds, dtype=np.float64), self.seconds.shape)
        return dataclasses.replace(self, scene_frames=scene_frames_at(scene, sec, "scene time"))

    def with_scene_speed(self, scene: SceneData, speed: float, anchor: Optional[float] = None) -> "CameraPath":
        """Scene time runs ``speed`` times as fast as the path clock, both equal at
        ``anchor`` (default: the path's first frame): 0.5 = slow motion, 0 = frozen."""
        a = float(self.seconds[0]) if anchor is None else float(anchor)
        return self.with_scene_time(scene, a + speed * (self.seconds - a))


# ---------------------------------------------------------------------- helpers
def log_seconds(scene: SceneData) -> np.ndarray:
    """(F,) seconds of every loaded frame since the first."""
    ts = np.asarray(scene.frame_timestamps, dtype=np.float64)
    return ts - ts[0]


def log_duration(scene: SceneData) -> float:
    return float(log_seconds(scene)[-1])


def scene_frames_at(scene: SceneData, seconds: np.ndarray, what: str = "time") -> np.ndarray:
    """(T,) fractional frame indices of ``seconds`` (T,) since the first frame; a time equal to
    a recorded timestamp gives that frame exactly. Times outside the log are refused."""
    seconds = np.asarray(seconds, dtype=np.float64)
    dur = log_duration(scene)
    bad = seconds[(seconds < -1e-9) | (seconds > dur + 1e-9)]
    if len(bad):
        raise ConfigError(f"{what} {float(bad[0]):.6g} s: outside the log (0 .. {dur:.6g} s since its first frame)")
    i0, i1, w = bracket(log_seconds(scene), np.clip(seconds, 0.0, dur))
    return i0 + w * (i1 - i0)


def rig_poses(scene: SceneData) -> np.ndarray:
    """(F, 4, 4) rig (ego) poses, x forward, y left, z up: the scene's ego poses, or, when it
    has none, the first camera's poses re-axed (OpenCV z forward -> x, -x -> y, -y -> z)."""
    if scene.ego_poses is not None:
        return np.asarray(scene.ego_poses, dtype=np.float64)
    c2w = np.asarray(scene.cameras[0].cam_to_world, dtype=np.float64)
    opencv_to_rig = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: rig axes in camera axes
    out = c2w.copy()
    out[:, :3, :3] = c2w[:, :3, :3] @ opencv_to_rig
    return out


def _camera_indices(scene: SceneData, cameras: Optional[Sequence[str]]) -> list[int]:
    if not cameras:
        return list(range(len(scene.cameras)))
    return [scene.camera_index(n) for n in cameras]


def recorded_fps(scene: SceneData) -> float:
    """The log's frame rate (1 / median frame interval; 10 when it has one frame)."""
    dt = np.diff(log_seconds(scene))
    return float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 10.0


def _path(scene: SceneData, cams: list[int], seconds: np.ndarray, frames: np.ndarray, c2w: np.ndarray,
          rig: np.ndarray, fps: float) -> CameraPath:
    return CameraPath(
        names=tuple(scene.cameras[c].name for c in cams),
        intrinsics=np.stack([np.asarray(scene.cameras[c].intrinsics, dtype=np.float64) for c in cams]),
        sizes=tuple((scene.cameras[c].width, scene.cameras[c].height) for c in cams),
        cam_to_world=c2w, seconds=np.asarray(seconds, dtype=np.float64),
        scene_frames=np.asarray(frames, dtype=np.float64), rig_to_world=rig, fps=float(fps))


# ---------------------------------------------------------------------- builders
def recorded_path(scene: SceneData, cameras: Optional[Sequence[str]] = None,
                  frames: Optional[Sequence[int]] = None, fps: Optional[float] = None,
                  frame_cap: int = DEFAULT_FRAME_CAP) -> CameraPath:
    """The recorded cameras at recorded ``frames`` (default: all), exactly as recorded; more
    than ``frame_cap`` frames are refused."""
    cams = _camera_indices(scene, cameras)
    idx = np.arange(scene.num_frames) if frames is None else np.asarray(list(frames), dtype=int)
    check_frame_count(len(idx), frame_cap, "camera path frames")
    if fps is not None:
        check_fps(fps, "fps")
    bad = idx[(idx < 0) | (idx >= scene.num_frames)]
    if len(bad):
        raise ConfigError(f"frame {int(bad[0])}: outside the loaded range 0..{scene.num_frames - 1}")
    c2w = np.stack([np.asarray(scene.cameras[c].cam_to_world, dtype=np.float64)[idx] for c in cams])
    return _path(scene, cams, log_seconds(scene)[idx], idx.astype(np.float64), c2w, rig_poses(scene)[idx],
                 fps or recorded_fps(scene))


def path_at_times(scene: SceneData, seconds: np.ndarray, cameras: Optional[Sequence[str]] = None,
                  fps: Optional[float] = None) -> CameraPath:
    """The recorded camera rig at any times ``seconds`` (T,) since the first frame: poses
    interpolated between the recorded frames (SLERP + linear); recorded times give the
    recorded poses exactly."""
    cams = _camera_indices(scene, cameras)
    frames = scene_frames_at(scene, seconds, "camera path time")
    known = np.arange(scene.num_frames, dtype=np.float64)
    c2w = np.stack([interpolate_poses(known, scene.cameras[c].cam_to_world, frames) for c in cams])
    rig = interpolate_poses(known, rig_poses(scene), frames)
    return _path(scene, cams, seconds, frames, c2w, rig, fps or recorded_fps(scene))


def interpolated_path(scene: SceneData, fps: float, cameras: Optional[Sequence[str]] = None,
                      start: float = 0.0, end: Optional[float] = None,
                      frame_cap: int = DEFAULT_FRAME_CAP) -> CameraPath:
    """The recorded rig resampled at ``fps`` (at most :data:`omnire.limits.MAX_FPS`) from
    ``start`` to ``end`` seconds (default: the whole log), poses interpolated between
    recorded frames; more than ``frame_cap`` frames are refused."""
    fps = check_fps(fps, "fps")
    dur = log_duration(scene)
    end = dur if end is None else float(end)
    if not 0.0 <= start <= end <= dur + 1e-9:
        raise ConfigError(f"camera path window {start} .. {end} s: must satisfy 0 <= start <= end <= {dur:.6g} "
                          "(the log's length in seconds)")
    n = int(np.floor((end - start) * fps + 1e-6)) + 1
    check_frame_count(n, frame_cap, f"camera path ({end - start:.6g} s at {fps:g} fps)")
    seconds = np.minimum(start + np.arange(n) / fps, dur)
    return path_at_times(scene, seconds, cameras, fps)


def _load_pose_file(path: Path, frame_cap: int) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise MissingFileError(f"{path}: camera path file not found (expected .npz or .json with 'seconds' (T,) "
                               "and 'rig_to_world' (T, 4, 4))")
    size, limit = path.stat().st_size, file_size_cap(frame_cap)
    if size > limit:
        raise ConfigError(f"{path}: {size} bytes is more than a camera path of at most {frame_cap} frames needs "
                          f"({limit} bytes; raise the frame cap with --frame-cap)")
    try:
        if path.suffix.lower() == ".json":
            raw = load_json(path, "camera path (JSON)")
            if not isinstance(raw, dict):
                raise ValueError("top level must be an object")
            return {k: np.asarray(v, dtype=np.float64) for k, v in raw.items()}
        with np.load(path, allow_pickle=False) as data:
            check_npz_rows(data, frame_cap, str(path))
            return {k: np.asarray(data[k], dtype=np.float64) for k in data.files}
    except (ValueError, OSError, TypeError, EOFError, zipfile.BadZipFile) as exc:
        raise ConfigError(f"{path}: cannot read the camera path ({exc})") from None


def file_path(scene: SceneData, path: Path, cameras: Optional[Sequence[str]] = None,
              fps: Optional[float] = None, frame_cap: int = DEFAULT_FRAME_CAP) -> CameraPath:
    """Rig poses from a file: ``seconds`` (T,) increasing path times since the log's first
    frame and ``rig_to_world`` (T, 4, 4) rig (ego) poses in the scene's world frame (x
    forward, y left, z up); optional ``scene_seconds`` (T,) the scene moment each frame
    shows (default: ``seconds``). Each camera is mounted on the rig as recorded (its
    camera-to-rig transform at the nearest recorded frame). npz or JSON (same keys). At most
    ``frame_cap`` frames; rig positions within the scene's extent plus
    :data:`omnire.limits.POSITION_MARGIN_M`; the frame rate within :data:`omnire.limits.MAX_FPS`."""
    path = Path(path)
    data = _load_pose_file(path, frame_cap)
    for key in ("seconds", "rig_to_world"):
        if key not in data:
            raise ConfigError(f"{path}: missing '{key}' (expected 'seconds' (T,) and 'rig_to_world' (T, 4, 4); "
                              f"found {sorted(data)})")
    sec, rig = data["seconds"], data["rig_to_world"]
    T = len(sec) if sec.ndim == 1 else -1
    if sec.ndim != 1 or T == 0 or rig.shape != (T, 4, 4):
        raise ConfigError(f"{path}: 'seconds' {sec.shape} must be (T,) and 'rig_to_world' {rig.shape} (T, 4, 4), T > 0")
    check_frame_count(T, frame_cap, f"{path}: 'seconds'")
    if not (np.isfinite(sec).all() and np.isfinite(rig).all()):
        raise ConfigError(f"{path}: non-finite values in 'seconds' or 'rig_to_world'")
    check_positions(rig[:, :3, 3], scene, f"{path}: 'rig_to_world'")
    if T > 1 and not np.all(np.diff(sec) > 0):
        raise ConfigError(f"{path}: 'seconds' must be strictly increasing")
    R = rig[:, :3, :3]
    orthonormal = np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-4)
    if not orthonormal or not np.allclose(np.linalg.det(R), 1, atol=1e-4):
        raise ConfigError(f"{path}: 'rig_to_world' rotations are not orthonormal (det +1)")
    scene_sec = data.get("scene_seconds", sec)
    if scene_sec.shape != sec.shape:
        raise ConfigError(f"{path}: 'scene_seconds' {scene_sec.shape} must be (T,) like 'seconds'")
    frames = scene_frames_at(scene, scene_sec, f"{path}: scene_seconds")
    cams = _camera_indices(scene, cameras)
    recorded_rig = rig_poses(scene)
    # mount each camera as recorded at the frame nearest to each path time
    near = np.clip(np.round(scene_frames_at(scene, np.clip(sec, 0, log_duration(scene)))).astype(int), 0,
                   scene.num_frames - 1)
    c2w = np.stack([np.linalg.inv(recorded_rig[near]) @ np.asarray(scene.cameras[c].cam_to_world)[near] for c in cams])
    c2w = rig[None] @ c2w
    if fps is None:
        fps = check_fps(float(1.0 / np.median(np.diff(sec))) if T > 1 else recorded_fps(scene),
                        f"{path}: the frame rate of 'seconds'")
    return _path(scene, cams, sec, frames, c2w, rig, check_fps(fps, "fps"))
