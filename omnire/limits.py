"""Stated limits on what a render request may ask for (frame rates, image sizes, frame
counts, positions), checked before any work so that a hostile or mistyped value is a
one-line error naming the field, never a multi-gigabyte allocation or an overflow.

The caps are far above any real use (a 240 fps video, 8192-pixel images, positions a
kilometre beyond everything the log recorded); the frame-count cap can be raised by a flag
(``omnire sim --frame-cap``).
"""
from __future__ import annotations

import math
import numpy as np

from omnire.errors import ConfigError

MAX_FPS = 240.0
"""Highest output frame rate (frames per second)."""
MAX_IMAGE_SIDE = 8192
"""Largest rendered image width or height, pixels."""
DEFAULT_FRAME_CAP = 20_000
"""Most output frames a camera path may have unless raised (1000 s at 20 fps)."""
MAX_MOTION_FRAMES = 100_000
"""Most frames a body-pose sequence may have (over 13 minutes at 120 fps)."""
POSITION_MARGIN_M = 1000.0
"""How far (metres) beyond the scene's extent a camera or an actor may be placed."""
BYTES_PER_PATH_FRAME = 2048
"""Camera-path file size allowed per frame of the cap (a JSON rig pose takes about 400 bytes)."""


def check_fps(fps: float, field: str) -> float:
    """``fps`` as a float in (0, MAX_FPS]; ``field`` names it in the error."""
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.floating, np.integer)):
        raise ConfigError(f"{field} {fps!r}: expected a number of frames per second")
    if not (math.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise ConfigError(f"{field} {fps}: must be a frame rate in (0, {MAX_FPS:g}]")
    return float(fps)


def check_image_size(width: int, height: int, field: str) -> None:
    """Both sides in 1..MAX_IMAGE_SIDE pixels."""
    for side, value in (("width", width), ("height", height)):
        if not 1 <= value <= MAX_IMAGE_SIDE:
            raise ConfigError(f"{field} {width}x{height}: the {side} must be 1..{MAX_IMAGE_SIDE} pixels")


def check_frame_count(count: int, cap: int, field: str, hint: str = "raise it with --frame-cap") -> None:
    """At most ``cap`` frames; ``hint`` says what to do otherwise."""
    if count > cap:
        raise ConfigError(f"{field}: {count} frames is more than the cap of {cap} ({hint})")


def scene_extent(scene) -> tuple[np.ndarray, np.ndarray]:
    """(3,) low and high corners of what the log recorded: every camera and rig position."""
    points = [np.asarray(c.cam_to_world, dtype=np.float64)[:, :3, 3] for c in scene.cameras]
    if scene.ego_poses is not None:
        points.append(np.asarray(scene.ego_poses, dtype=np.float64)[:, :3, 3])
    allp = np.concatenate(points)
    return allp.min(axis=0), allp.max(axis=0)


def check_positions(points: np.ndarray, scene, field: str, margin: float = POSITION_MARGIN_M) -> None:
    """Refuse world positions (N, 2) or (N, 3) outside the scene's extent grown by ``margin``
    metres (or not finite)."""
    pts = np.asarray(points, dtype=np.float64).reshape(len(points), -1)
    if len(pts) == 0:
        return
    lo, hi = scene_extent(scene)
    d = pts.shape[1]
    inside = np.isfinite(pts).all(axis=1) & (pts >= lo[:d] - margin).all(axis=1) & (pts <= hi[:d] + margin).all(axis=1)
    if not inside.all():
        k = int(np.argmin(inside))
        box = ", ".join(f"{'xyz'[i]} {lo[i] - margin:.0f}..{hi[i] + margin:.0f}" for i in range(d))
        raise ConfigError(f"{field}: position {np.array2string(pts[k], precision=6)} lies outside the scene's "
                          f"extent plus {margin:.0f} m ({box})")


def check_offset(offset, scene, field: str, margin: float = POSITION_MARGIN_M) -> None:
    """Refuse a displacement longer than the scene's extent plus ``margin`` metres."""
    vec = np.atleast_1d(np.asarray(offset, dtype=np.float64))
    lo, hi = scene_extent(scene)
    reach = float(np.linalg.norm(hi - lo)) + margin
    length = float(np.linalg.norm(vec)) if np.isfinite(vec).all() else math.inf
    if length > reach:
        raise ConfigError(f"{field}: an offset of {length:.6g} m is longer than the scene's extent plus "
                          f"{margin:.0f} m ({reach:.0f} m)")


def file_size_cap(cap: int) -> int:
    """Largest camera-path file accepted for a frame cap of ``cap``."""
    return cap * BYTES_PER_PATH_FRAME + (1 << 16)


def check_npz_rows(npz, cap: int, source: str, hint: str = "raise it with --frame-cap") -> None:
    """Refuse an open npz (``numpy.load`` result) any of whose arrays has more than ``cap``
    rows, reading only the array headers: a compressed file of zeros that would unpack to
    gigabytes is refused before anything is decompressed."""
    for key in npz.files:
        with npz.zip.open(f"{key}.npy") as f:
            version = np.lib.format.read_magic(f)
            shape, _, _ = (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
                           else np.lib.format.read_array_header_2_0(f))
        check_frame_count(int(shape[0]) if shape else 1, cap, f"{source}: '{key}'", hint)
