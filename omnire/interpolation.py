"""Interpolation along a log: the one helper behind box poses, body poses, ego and camera
paths at times between (or frames other than) the observed ones.

A query is bracketed by two known samples (:func:`bracket`); rotations are SLERPed and
translations interpolated linearly between them (:func:`interpolate_poses`). Outside the
known range the nearest sample is held. Works on numpy arrays (readers, scene preparation)
and torch tensors (nodes) alike.
"""
from __future__ import annotations

from typing import Union

import numpy as np
import torch

from omnire.geometry import (axis_angle_to_rotmat, rotmat_to_axis_angle, slerp_rotmats)

Array = Union[np.ndarray, torch.Tensor]


def bracket(known: np.ndarray, query: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For increasing ``known`` (K,) positions (times or frame indices) and ``query`` (Q,)
    (or a scalar), the indices (Q,) of the enclosing known samples and the weight (Q,) of the
    second: value(q) = (1 - w) value[i0] + w value[i1]. A query equal to a known position
    gives i0 = i1 and w = 0 exactly; outside the range the nearest sample is held."""
    known = np.asarray(known, dtype=np.float64)
    q = np.atleast_1d(np.asarray(query, dtype=np.float64))
    if known.ndim != 1 or len(known) == 0:
        raise ValueError(f"bracket: known positions must be a non-empty 1-D array, got shape {known.shape}")
    if len(known) > 1 and not np.all(np.diff(known) > 0):
        raise ValueError("bracket: known positions must be strictly increasing")
    i1 = np.searchsorted(known, q, side="left").clip(0, len(known) - 1)
    i0 = np.where(known[i1] > q, np.maximum(i1 - 1, 0), i1)
    span = known[i1] - known[i0]
    w = np.where(span > 0, (q - known[i0]) / np.where(span > 0, span, 1.0), 0.0)
    w = np.where(q <= known[0], 0.0, np.where(q >= known[-1], 0.0, w))
    i1 = np.where(w == 0, i0, i1)
    return i0, i1, w


def interpolate_rotations(R: Array, i0, i1, w) -> Array:
    """SLERP of rotations ``R`` (K, ..., 3, 3) between rows i0 (Q,) and i1 (Q,) with weights w
    (Q,): (Q, ..., 3, 3). Rows with w = 0 are returned exactly."""
    if isinstance(R, np.ndarray) and R.ndim == 3:
        # (K, 3, 3) queried many times (a LiDAR sweep: 1e5 returns between a few poses):
        # each distinct bracket's relative rotation once as an axis and angle (shorter arc),
        # then per query R0 exp(w angle [axis]x) by Rodrigues' formula in numpy: the geodesic
        # quaternion SLERP follows, without per-query torch calls (10x slower on small arrays).
        w = np.asarray(w, dtype=np.float64)
        out = R[i0].copy()
        mix = w > 0
        if mix.any():
            pair, inverse = np.unique(np.stack([i0[mix], i1[mix]], 1), axis=0, return_inverse=True)
            inverse = inverse.reshape(-1)
            R0 = R[pair[:, 0]]  # (P, 3, 3)
            rotvec = np.asarray(rotmat_to_axis_angle(np.swapaxes(R0, 1, 2) @ R[pair[:, 1]]))  # (P, 3)
            angle = np.linalg.norm(rotvec, axis=1)  # (P,) in [0, pi]
            x, y, z = (rotvec / np.where(angle > 0, angle, 1.0)[:, None]).T
            zero = np.zeros_like(x)
            K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], 1).reshape(-1, 3, 3)  # [axis]x
            phi = w[mix] * angle[inverse]  # (Q',)
            exp = (np.eye(3) + np.sin(phi)[:, None, None] * K[inverse]
                   + (1 - np.cos(phi))[:, None, None] * (K @ K)[inverse])
            out[mix] = R0[inverse] @ exp
        return out
    R0, R1 = R[i0], R[i1]
    if isinstance(R, np.ndarray):
        w = np.asarray(w, dtype=np.float64)
        wb = np.broadcast_to(w.reshape((-1,) + (1,) * (R0.ndim - 3)), R0.shape[:-2])
        out = R0.copy()
        mix = wb > 0
        if mix.any():
            out[mix] = slerp_rotmats(R0[mix], R1[mix], np.ascontiguousarray(wb[mix]))
        return out
    w = torch.as_tensor(w, dtype=R.dtype, device=R.device)
    wb = w.reshape((-1,) + (1,) * (R0.ndim - 3)).expand(R0.shape[:-2])
    mix = wb > 0
    if not bool(mix.any()):
        return R0
    return R0.index_put(torch.nonzero(mix, as_tuple=True), slerp_rotmats(R0[mix], R1[mix], wb[mix]))


def interpolate_vectors(x: Array, i0, i1, w) -> Array:
    """Linear interpolation of ``x`` (K, ...) between rows i0 and i1 with weights w (Q,)."""
    if isinstance(x, np.ndarray):
        wb = np.asarray(w, dtype=np.float64).reshape((-1,) + (1,) * (x.ndim - 1))
        return x[i0] * (1 - wb) + x[i1] * wb
    wb = torch.as_tensor(w, dtype=x.dtype, device=x.device).reshape((-1,) + (1,) * (x.ndim - 1))
    return x[i0] * (1 - wb) + x[i1] * wb


def interpolate_poses(known: np.ndarray, poses: np.ndarray, query: np.ndarray | float) -> np.ndarray:
    """Rigid poses (K, 4, 4) at increasing positions ``known`` (K,) -> poses (Q, 4, 4) at
    ``query``: rotations SLERPed, translations linear, the nearest held outside the range.
    Known positions are returned exactly."""
    poses = np.asarray(poses, dtype=np.float64)
    i0, i1, w = bracket(known, query)
    out = np.tile(np.eye(4), (len(i0), 1, 1))
    out[:, :3, :3] = interpolate_rotations(poses[:, :3, :3], i0, i1, w)
    out[:, :3, 3] = interpolate_vectors(poses[:, :3, 3], i0, i1, w)
    return out


def interpolate_track(times: np.ndarray, poses: np.ndarray, present: np.ndarray, query: np.ndarray,
                      max_gap: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """An annotated track resampled at ``query`` times (Q,): poses (K, 4, 4) at ``times``
    (K,), valid where ``present`` (K,). A query inside the annotated span whose enclosing
    annotations are at most ``max_gap`` apart is interpolated; others are absent. Returns
    (poses (Q, 4, 4), present (Q,) bool)."""
    times = np.asarray(times, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    keep = np.asarray(present, bool)
    out = np.tile(np.eye(4), (len(query), 1, 1))
    if keep.sum() == 0:
        return out, np.zeros(len(query), bool)
    t, P = times[keep], np.asarray(poses, dtype=np.float64)[keep]
    i0, i1, w = bracket(t, query)
    inside = (query >= t[0]) & (query <= t[-1]) & ((t[i1] - t[i0]) <= max_gap)
    out[inside] = interpolate_poses(t, P, query[inside])
    return out, inside


def extend_poses(known: np.ndarray, poses: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """A pose track (K, 4, 4) at increasing ``known`` times (K,), K >= 2, with one sample
    added ``margin`` seconds before the first and after the last, continuing the first and
    last step at constant velocity and turn rate (translation linear, rotation by the same
    axis-angle per second), so :func:`interpolate_poses` extrapolates instead of holding
    (a LiDAR sweep of the last frame runs past the last pose). Returns (K + 2,) and
    (K + 2, 4, 4)."""
    known = np.asarray(known, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if known.ndim != 1 or len(known) < 2 or poses.shape != (len(known), 4, 4) or not margin > 0:
        raise ValueError(f"extend_poses: known {known.shape}, poses {poses.shape}, margin {margin}; expected "
                         "(K,) with K >= 2, (K, 4, 4) and margin > 0")

    def beyond(a: np.ndarray, b: np.ndarray, dt: float) -> np.ndarray:  # pose ``margin`` past b, moving a -> b in dt
        s = margin / dt
        out = np.eye(4)
        turn = rotmat_to_axis_angle(b[:3, :3] @ a[:3, :3].T) * s  # world-frame turn, scaled
        out[:3, :3] = axis_angle_to_rotmat(turn) @ b[:3, :3]
        out[:3, 3] = b[:3, 3] + (b[:3, 3] - a[:3, 3]) * s
        return out

    first = beyond(poses[1], poses[0], known[1] - known[0])
    last = beyond(poses[-2], poses[-1], known[-1] - known[-2])
    return (np.concatenate([[known[0] - margin], known, [known[-1] + margin]]),
            np.concatenate([first[None], poses, last[None]]))
