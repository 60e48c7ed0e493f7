"""Validation of request values at the server's boundary: poses, times, image sizes.

Every check raises :class:`~omnire_serve.errors.RequestError` naming the request field, so
a bad value never reaches the renderer.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from omnire_serve.errors import RequestError

ORTHONORMAL_TOLERANCE = 1e-3
"""How far R R^T may be from the identity (clients often send float32 poses)."""


@dataclasses.dataclass(frozen=True)
class Limits:
    """What a request may ask for. ``margin``: metres a pose may lie outside the scene's
    extent (the box around every recorded camera, ego and actor position and LiDAR point); ``max_pixels``: width x height of
    one image; ``max_side``: the longest image side; ``max_lidar_rays``: rays of one LiDAR
    revolution (beams x azimuth steps); ``max_json_rays``: the most rays a sweep answered as
    JSON may have (npz has no such limit)."""

    margin: float = 50.0
    max_pixels: int = 960 * 540
    max_side: int = 4096
    max_body_bytes: int = 8 * 1024 * 1024
    max_sessions: int = 8
    max_lidar_rays: int = 64 * 4096
    max_json_rays: int = 32 * 1024


def pose_matrix(value, field: str, extent: tuple[np.ndarray, np.ndarray], margin: float) -> np.ndarray:
    """A (4, 4) float64 rigid pose from a nested list: finite, bottom row (0, 0, 0, 1),
    rotation orthonormal with det +1, translation inside ``extent`` ((3,) low, (3,) high)
    grown by ``margin`` metres."""
    try:
        P = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RequestError(field, "expected a 4x4 matrix of numbers (a list of 4 rows of 4)") from None
    if P.shape != (4, 4):
        raise RequestError(field, f"expected a 4x4 matrix (a list of 4 rows of 4 numbers); got shape {P.shape}")
    if not np.isfinite(P).all():
        raise RequestError(field, "non-finite value (NaN or infinity) in the pose")
    if not np.allclose(P[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise RequestError(field, f"bottom row {P[3].tolist()} must be [0, 0, 0, 1]")
    R = P[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > ORTHONORMAL_TOLERANCE or abs(np.linalg.det(R) - 1.0) > ORTHONORMAL_TOLERANCE:
        raise RequestError(field, "the 3x3 rotation block is not orthonormal with determinant +1")
    lo, hi = extent
    t = P[:3, 3]
    if np.any(t < lo - margin) or np.any(t > hi + margin):
        raise RequestError(field, f"position {np.round(t, 2).tolist()} lies outside the scene "
                                  f"({np.round(lo, 1).tolist()} .. {np.round(hi, 1).tolist()} m, plus a "
                                  f"margin of {margin:g} m)")
    return P


def image_size(width, height, default: tuple[int, int], limits: Limits, field: str = "") -> tuple[int, int]:
    """(width, height): the request's, or ``default`` when both are absent."""
    prefix = f"{field}." if field else ""
    if width is None and height is None:
        return default
    if width is None or height is None:
        raise RequestError(prefix + ("width" if width is None else "height"), "give both width and height, or neither")
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise RequestError(prefix + name, f"{v!r}: expected a positive integer (pixels)")
        if v > limits.max_side:
            raise RequestError(prefix + name, f"{v} pixels is more than the limit of {limits.max_side}", 413)
    if width * height > limits.max_pixels:
        raise RequestError(prefix + "width", f"{width}x{height} = {width * height} pixels is more than the limit of "
                                             f"{limits.max_pixels} per image (omnire serve --max-pixels)", 413)
    return int(width), int(height)
