"""Rotations and rigid transforms: the one implementation of each conversion in the tree.

Quaternions are wxyz (docs/conventions.md, "Rotations"). Every function takes torch tensors and is
differentiable; each also accepts numpy arrays (computed in float64, returned as numpy), so
readers and the body pipeline use the same code as the nodes.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, TypeVar

import numpy as np
import torch

F = TypeVar("F", bound=Callable[..., Any])


def numpy_compatible(fn: F) -> F:
    """Let a torch function take numpy arrays (or plain floats): when no argument is a
    tensor, arrays and floats are converted to float64 tensors and the result back to numpy
    (tuples element-wise). Integer arguments (axis numbers) are passed through."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        values = list(args) + list(kwargs.values())
        if any(torch.is_tensor(a) for a in values) or not any(
                isinstance(a, (np.ndarray, float, np.floating)) for a in values):
            return fn(*args, **kwargs)

        def to_t(a: Any) -> Any:
            if isinstance(a, (np.ndarray, float, np.floating)):
                return torch.from_numpy(np.array(a, dtype=np.float64))
            return a

        out = fn(*(to_t(a) for a in args), **{k: to_t(v) for k, v in kwargs.items()})
        if isinstance(out, tuple):
            return tuple(o.numpy() if torch.is_tensor(o) else o for o in out)
        return out.numpy()

    return wrapper  # type: ignore[return-value]


def quat_left_matrix(a: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz quaternions -> (..., 4, 4) L with ``quat_multiply(a, b) == L @ b``: a
    product with one fixed quaternion as a single matrix product (forward and backward)."""
    w, x, y, z = a.unbind(-1)
    return torch.stack([torch.stack([w, -x, -y, -z], -1), torch.stack([x, w, -z, y], -1),
                        torch.stack([y, z, w, -x], -1), torch.stack([z, -y, x, w], -1)], -2)


@numpy_compatible
def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of (..., 4) wxyz quaternions (broadcasting)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


@numpy_compatible
def normalize_quats(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz of any norm -> unit quaternions; zero quaternions become the identity
    (with finite gradients), as the rasterizer contract requires."""
    norm2 = (q * q).sum(-1, keepdim=True)
    zero = norm2 < 1e-24
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    safe = torch.where(zero, identity, q)
    return safe * torch.rsqrt(torch.where(zero, torch.ones_like(norm2), norm2))


@numpy_compatible
def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz of any norm (normalised here; zero = identity) -> (..., 3, 3)."""
    w, x, y, z = normalize_quats(q).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


# rotmat_to_quat: the radicands r = 1 + [t, 2 m00 - t, 2 m11 - t, 2 m22 - t] (t the trace) are
# 4 w^2, 4 x^2, 4 y^2, 4 z^2; branch b takes the components (w, x, y, z) from these columns of
# [r_w, r_x, r_y, r_z, m21 - m12, m02 - m20, m10 - m01, m01 + m10, m02 + m20, m12 + m21], each over
# 2 sqrt(r_b) (its own component r_b / (2 sqrt(r_b)) = sqrt(r_b) / 2).
_BRANCH_COLUMNS = ((0, 4, 5, 6), (4, 1, 7, 8), (5, 7, 2, 9), (6, 8, 9, 3))


@numpy_compatible
def rotmat_to_quat(R: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 4) unit wxyz with w >= 0.

    Shepperd's method with kornia's ``rotation_matrix_to_quaternion`` branch choice (w when
    the trace is positive, else the axis of the largest diagonal entry, ties to the later
    axis), so the same numbers wherever the chosen radicand exceeds ``eps`` (every rotation:
    it is at least 1); a radicand at or below ``eps`` counts as ``eps``, with a zero
    gradient. A fraction of kornia's tensor operations, forward and backward: this runs
    several times per training step (box poses, camera-pose moves, and per point in SMPL
    skinning)."""
    shape = R.shape[:-2]
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.reshape(-1, 9).unbind(-1)
    t = m00 + m11 + m22
    r = torch.stack([t, 2 * m00 - t, 2 * m11 - t, 2 * m22 - t], -1) + 1.0  # (M, 4)
    feats = torch.cat([r, torch.stack([m21 - m12, m02 - m20, m10 - m01, m01 + m10, m02 + m20, m12 + m21], -1)], -1)
    with torch.no_grad():
        # argmax of (m22, m11, m00) returns the first largest: the later axis of a tie
        branch = torch.where(t > 0, 0, 3 - torch.stack([m22, m11, m00], -1).argmax(-1))
        columns = torch.tensor(_BRANCH_COLUMNS, device=R.device).index_select(0, branch)  # (M, 4)
    numerators = feats.gather(-1, columns)
    sq = 2.0 * torch.sqrt(r.gather(-1, branch[:, None]).clamp_min(eps))  # (M, 1)
    q = numerators / torch.where(numerators[:, :1] < 0, -sq, sq)  # w >= 0
    return q.reshape(*shape, 4)


@numpy_compatible
def axis_angle_to_rotmat(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle -> (..., 3, 3), differentiable at 0 (Rodrigues with a Taylor
    expansion for tiny angles)."""
    theta2 = (v * v).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = theta2 < 1e-12
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / torch.where(small, torch.ones_like(theta2), theta2))
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*v.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=v.dtype, device=v.device).expand_as(Kx)
    return eye + a * Kx + b * (Kx @ Kx)


@numpy_compatible
def rotmat_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 3) axis-angle with angle in [0, pi]."""
    q = rotmat_to_quat(R)
    xyz = q[..., 1:]
    s = xyz.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., :1])
    # angle / sin(angle / 2) -> 2 as the angle goes to 0
    factor = torch.where(s < 1e-8, torch.full_like(s, 2.0), angle / s.clamp_min(1e-12))
    return xyz * factor


@numpy_compatible
def slerp_quats(q0: torch.Tensor, q1: torch.Tensor, w: torch.Tensor | float) -> torch.Tensor:
    """Spherical interpolation of (..., 4) unit quaternions along the shorter arc; ``w``
    (...,) or a float, 0 gives q0 and 1 gives q1."""
    w = torch.as_tensor(w, dtype=q0.dtype, device=q0.device)
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    theta = torch.arccos(dot.abs().clamp(max=1 - 1e-7))
    s = torch.sin(theta)
    w = w[..., None] if w.ndim else w
    near = s < 1e-5
    s_safe = torch.where(near, torch.ones_like(s), s)
    a = torch.where(near, 1 - w, torch.sin((1 - w) * theta) / s_safe)
    b = torch.where(near, w, torch.sin(w * theta) / s_safe)
    return a * q0 + b * q1


@numpy_compatible
def slerp_rotmats(R0: torch.Tensor, R1: torch.Tensor, w: torch.Tensor | float) -> torch.Tensor:
    """SLERP between (..., 3, 3) rotations with weights ``w`` (...,) or a float."""
    return quat_to_rotmat(slerp_quats(rotmat_to_quat(R0), rotmat_to_quat(R1), w))


@numpy_compatible
def axis_rotation(axis: int, angle: torch.Tensor) -> torch.Tensor:
    """(...,) angles in radians -> (..., 3, 3) right-handed rotations about coordinate axis
    ``axis`` (0 = x, 1 = y, 2 = z)."""
    if axis not in (0, 1, 2):
        raise ValueError(f"axis_rotation: axis must be 0, 1 or 2, got {axis}")
    c, s = torch.cos(angle), torch.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = torch.zeros(*angle.shape, 3, 3, dtype=angle.dtype, device=angle.device)
    R[..., axis, axis] = 1.0
    R[..., i, i], R[..., i, j], R[..., j, i], R[..., j, j] = c, -s, s, c
    return R


def rot_z(angle: torch.Tensor) -> torch.Tensor:
    """(...,) angles in radians -> (..., 3, 3) rotations about +z (numpy arrays and floats too)."""
    return axis_rotation(2, angle)


@numpy_compatible
def lowpass_conics(cov2d: torch.Tensor, eps: float, valid: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA's 2D step: projected covariances (N, 2, 2) plus ``eps`` on the diagonal (the
    low-pass filter), inverted. Returns conics (N, 3) (a', b', c') of the inverse
    [[a', b'], [b', c']] (finite, arbitrary where not ``ok``), the low-passed diagonal a, c
    (N,) each, the determinant (N,) and ``ok`` (N,) = ``valid`` (N,) & determinant > 0."""
    a = cov2d[:, 0, 0] + eps
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + eps
    det = a * c - b * b
    ok = valid & (det > 0)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    return torch.stack([c / det_safe, -b / det_safe, a / det_safe], -1), torch.stack([a, c], -1), det, ok


@numpy_compatible
def quat_to_se3(q: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz rotations (normalised here, as in :func:`quat_to_rotmat`) and (..., 3)
    translations -> (..., 4, 4) rigid transforms x -> R(q) x + t."""
    R = quat_to_rotmat(q)
    out = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    out[..., :3, :3] = R
    out[..., :3, 3] = t
    out[..., 3, 3] = 1
    return out


@numpy_compatible
def invert_se3(T: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) rigid transform -> its inverse."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    out = torch.zeros_like(T)
    out[..., :3, :3] = R.transpose(-1, -2)
    out[..., :3, 3:] = -R.transpose(-1, -2) @ t
    out[..., 3, 3] = 1
    return out


def rigid(R: "np.ndarray | None" = None, t: Any = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) float64 numpy transform from a rotation ``R`` (3, 3) (identity if None) and a
    translation ``t`` (3,): the builder readers, writers and the scene generator share."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T
