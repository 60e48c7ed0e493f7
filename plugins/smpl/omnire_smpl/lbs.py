"""Batched forward kinematics and linear blend skinning in torch (SMPL conventions).

Same maths as the float64 numpy reference :mod:`omnire_body.lbs` (tested against it), but
batched over P people. Skinning weights are stored sparse per point (its K largest joint
weights, K = the most joints any template vertex uses, 6 for the shipped template); the
blend turns them into one (M_p, 24) x (24, 12) product per person when each person's
points are contiguous, else gathers the K transforms of each point.
"""
from __future__ import annotations

import torch


def forward_kinematics(joints: torch.Tensor, parents: list[int], rots: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Posed joints and skinning transforms of P bodies.

    Args:
        joints: (P, 24, 3) rest joint positions.
        parents: 24 parent indices (parents[0] = -1, parents[j] < j).
        rots: (P, 24, 3, 3) joint rotations relative to the parents (rots[:, 0]: root).
    Returns:
        posed joints (P, 24, 3) and skinning transforms A (P, 24, 3, 4) with
        A_j = G_j [I | -J_j] (the joint's world transform with the rest placement removed).
    """
    R_world = [rots[:, 0]]
    t_world = [joints[:, 0]]
    for j in range(1, joints.shape[1]):
        p = parents[j]
        offset = joints[:, j] - joints[:, p]  # bone in the rest pose
        R_world.append(R_world[p] @ rots[:, j])
        t_world.append(t_world[p] + (R_world[p] @ offset[..., None])[..., 0])
    R = torch.stack(R_world, 1)  # (P, 24, 3, 3)
    t = torch.stack(t_world, 1)  # (P, 24, 3)
    A = torch.cat([R, (t - (R @ joints[..., None])[..., 0])[..., None]], dim=-1)
    return t, A


def blend_transforms(A: torch.Tensor, slot: torch.Tensor, joint_idx: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Per-point blended transform sum_k w_k A[slot, j_k].

    Args:
        A: (P, 24, 3, 4) skinning transforms.
        slot: (M,) body index of each point into A.
        joint_idx: (M, K) joint indices; weights: (M, K) their weights.
    Returns:
        (M, 3, 4).

    When ``slot`` is non-decreasing (the points of each body contiguous, as nodes gather
    them) each body's points are one matrix product, (M_p, 24) weights (zero where a point
    has no weight) times (24, 12) transforms, and the gradient of A is the transposed
    product: a few products instead of gathering M K transforms and scattering their
    gradients back. Other orders gather per point. Both give the same numbers up to the
    order of float summation.
    """
    P, J = A.shape[:2]
    M, K = joint_idx.shape
    if M > 0 and not bool((slot[1:] < slot[:-1]).any()):
        dense = torch.zeros(M, J, dtype=weights.dtype, device=weights.device)
        dense.scatter_add_(1, joint_idx, weights)  # (M, 24)
        counts = torch.bincount(slot, minlength=P).tolist()
        per_body = A.reshape(P, J, 12)
        parts = [w @ per_body[p] for p, w in enumerate(dense.split(counts)) if counts[p]]
        return torch.cat(parts).reshape(M, 3, 4)
    flat = A.reshape(P * J, 12)
    # index_select, not advanced indexing: its backward is index_add_, several times faster on
    # the CPU than the accumulating index_put_ of ``flat[idx]``
    picked = flat.index_select(0, (slot[:, None] * J + joint_idx).reshape(-1)).reshape(M, K, 12)
    return (weights[..., None] * picked).sum(1).reshape(-1, 3, 4)


def sparse_weights(weights: torch.Tensor, k: int | None = None, eps: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 24) dense weights -> (V, K) joint indices and renormalised weights. ``k`` defaults
    to the largest number of non-zero weights in a row (exact)."""
    if k is None:
        k = max(1, int((weights > eps).sum(1).max()))
    w, idx = weights.topk(k, dim=1)
    return idx, w / w.sum(1, keepdim=True).clamp_min(eps)
