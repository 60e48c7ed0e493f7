"""Batched forward kinematics and linear blend skinning in torch (SMPL conventions).

Same maths as the float64 numpy reference :mod:`omnire_body.lbs` (tested against it), but
batched over P people. Skinning weights are stored sparse per point (its K largest joint
weights, K = the most joints any template vertex uses, 6 for the shipped template); the
blend turns them into one (M_p, 24) x (24, 12) product per person when each person's
points are contiguous, else gathers the K transforms of each point.
"""
from __future__ import annotations

import torch


def kinematic_levels(parents: list[int]) -> list[list[int]]:
    """Joints grouped by depth in the tree (level 0: the root), each level's joints increasing.
    Every joint's parent is in the level before its own."""
    depth = [0] * len(parents)
    for j in range(1, len(parents)):
        if not 0 <= parents[j] < j:
            raise ValueError(f"parents[{j}] = {parents[j]}: expected a parent index in [0, {j})")
        depth[j] = depth[parents[j]] + 1
    return [[j for j in range(len(parents)) if depth[j] == d] for d in range(max(depth) + 1)]


def forward_kinematics(joints: torch.Tensor, parents: list[int], rots: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Posed joints and skinning transforms of P bodies.

    Args:
        joints: (P, 24, 3) rest joint positions.
        parents: 24 parent indices (parents[0] = -1, parents[j] < j).
        rots: (P, 24, 3, 3) joint rotations relative to the parents (rots[:, 0]: root).
    Returns:
        posed joints (P, 24, 3) and skinning transforms A (P, 24, 3, 4) with
        A_j = G_j [I | -J_j] (the joint's world transform with the rest placement removed).

    The chain runs one tree level at a time (9 levels for SMPL's 24 joints): a level's
    joints take their parents' world transforms together, so the forward and backward pass
    are a few batched products per level instead of per joint (the same products).
    """
    levels = kinematic_levels(parents)
    J = joints.shape[1]
    offset = joints[:, 1:] - joints[:, parents[1:]]  # (P, J - 1, 3) bones in the rest pose
    R_lv, t_lv = [rots[:, :1]], [joints[:, :1]]  # per level: (P, n, 3, 3), (P, n, 3)
    for prev, level in zip(levels, levels[1:]):
        slot = {j: k for k, j in enumerate(prev)}
        up = torch.tensor([slot[parents[j]] for j in level], device=joints.device)
        here = torch.tensor(level, device=joints.device)
        R_up, t_up = R_lv[-1].index_select(1, up), t_lv[-1].index_select(1, up)
        R_lv.append(R_up @ rots.index_select(1, here))
        t_lv.append(t_up + (R_up @ offset.index_select(1, here - 1)[..., None])[..., 0])
    order = torch.tensor([j for level in levels for j in level], device=joints.device)
    back = torch.empty_like(order)
    back[order] = torch.arange(J, device=joints.device)  # joint j sits at back[j] of the levels' concatenation
    R = torch.cat(R_lv, 1).index_select(1, back)  # (P, 24, 3, 3)
    t = torch.cat(t_lv, 1).index_select(1, back)  # (P, 24, 3)
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
