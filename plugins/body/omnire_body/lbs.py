"""Forward kinematics and linear blend skinning in numpy (float64), SMPL conventions.

Pose = global orientation (3, 3) of the pelvis plus 23 body-joint rotations (23, 3, 3),
each relative to its parent, in SMPL joint order. Every function accepts an optional
leading batch dimension B on the pose arrays; outputs then carry it too.

Posed vertex (SMPL): ``v' = sum_j w_j * A_j @ v_shaped + transl`` where ``A_j`` is the
skinning transform of joint j (world transform of the joint with its rest position
removed), the global rotation turns the body about the pelvis joint, and ``transl`` moves
the result. The torch SMPL node is tested against these functions.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from omnire_body.template import NUM_JOINTS, BodyTemplate


@dataclasses.dataclass
class LBSOutput:
    """Posed body. vertices (..., V, 3); joints (..., 24, 3); transforms (..., 24, 4, 4)
    skinning transforms (joint world transform times the inverse rest placement)."""

    vertices: np.ndarray
    joints: np.ndarray
    transforms: np.ndarray


def _full_pose(global_orient: np.ndarray, body_pose: np.ndarray) -> tuple[np.ndarray, bool]:
    """Stack to (B, 24, 3, 3); the flag says whether the input was unbatched."""
    go = np.asarray(global_orient, dtype=np.float64)
    bp = np.asarray(body_pose, dtype=np.float64)
    single = go.ndim == 2
    if single:
        go, bp = go[None], bp[None]
    if go.shape[1:] != (3, 3) or bp.shape[1:] != (NUM_JOINTS - 1, 3, 3) or go.shape[0] != bp.shape[0]:
        raise ValueError(f"expected global_orient (B,3,3) and body_pose (B,23,3,3), got {go.shape} and {bp.shape}")
    return np.concatenate([go[:, None], bp], axis=1), single


def forward_kinematics(
    joints: np.ndarray, parents: np.ndarray, global_orient: np.ndarray, body_pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Posed joint positions and skinning transforms.

    Args:
        joints: (24, 3) or (B, 24, 3) rest joint positions.
        parents: (24,) parent indices with parents[j] < j.
        global_orient: (3, 3) or (B, 3, 3); body_pose: (23, 3, 3) or (B, 23, 3, 3).
    Returns:
        posed joints (B?, 24, 3) and skinning transforms (B?, 24, 4, 4).
    """
    rots, single = _full_pose(global_orient, body_pose)  # (B, 24, 3, 3)
    B = rots.shape[0]
    J = np.broadcast_to(np.asarray(joints, dtype=np.float64), (B, NUM_JOINTS, 3))
    world = np.zeros((B, NUM_JOINTS, 4, 4))
    world[:, :, 3, 3] = 1.0
    world[:, 0, :3, :3] = rots[:, 0]
    world[:, 0, :3, 3] = J[:, 0]
    for j in range(1, NUM_JOINTS):
        p = parents[j]
        local = np.zeros((B, 4, 4))
        local[:, :3, :3] = rots[:, j]
        local[:, :3, 3] = J[:, j] - J[:, p]  # offset from the parent in the rest pose
        local[:, 3, 3] = 1.0
        world[:, j] = world[:, p] @ local
    posed = world[:, :, :3, 3].copy()  # (B, 24, 3)
    skin = world.copy()
    # Remove the rest placement: A_j = G_j @ [I, -J_j].
    skin[:, :, :3, 3] -= np.einsum("bjkl,bjl->bjk", world[:, :, :3, :3], J)
    if single:
        return posed[0], skin[0]
    return posed, skin


def lbs(
    template: BodyTemplate,
    global_orient: np.ndarray,
    body_pose: np.ndarray,
    betas: Optional[np.ndarray] = None,
    transl: Optional[np.ndarray] = None,
    pose_blend: bool = True,
) -> LBSOutput:
    """Pose the template.

    Args:
        template: body template (SMPL canonical frame).
        global_orient: (3, 3) or (B, 3, 3) pelvis rotation (turns the body about the pelvis).
        body_pose: (23, 3, 3) or (B, 23, 3, 3) joint rotations relative to the parents.
        betas: optional (K,) or (B, K) shape coefficients (used when the template has shapedirs).
        transl: optional (3,) or (B, 3) translation added last.
        pose_blend: add pose blend shapes when the template has posedirs.
    Returns:
        :class:`LBSOutput` with vertices (B?, V, 3), joints (B?, 24, 3), transforms.
    """
    rots, single = _full_pose(global_orient, body_pose)
    B = rots.shape[0]
    V = template.num_vertices
    verts = np.broadcast_to(template.vertices, (B, V, 3)).copy()  # (B, V, 3)
    joints = np.broadcast_to(template.joints, (B, NUM_JOINTS, 3)).copy()
    if betas is not None and template.shapedirs is not None:
        b = np.atleast_2d(np.asarray(betas, dtype=np.float64))  # (B or 1, K)
        k = min(b.shape[1], template.shapedirs.shape[2])
        verts = verts + np.einsum("vck,bk->bvc", template.shapedirs[:, :, :k], b[:, :k])
        if template.J_regressor is not None:
            joints = np.einsum("jv,bvc->bjc", template.J_regressor, verts)
    if pose_blend and template.posedirs is not None:
        feat = (rots[:, 1:] - np.eye(3)).reshape(B, -1)  # (B, 207)
        verts = verts + np.einsum("vcp,bp->bvc", template.posedirs, feat)
    posed_joints, skin = forward_kinematics(joints, template.parents, rots[:, 0], rots[:, 1:])
    # Blend the 24 transforms per vertex as one BLAS matmul: (V, 24) @ (24, B*16).
    A = (template.weights @ skin.transpose(1, 0, 2, 3).reshape(NUM_JOINTS, B * 16))
    A = A.reshape(V, B, 4, 4).transpose(1, 0, 2, 3)  # (B, V, 4, 4)
    out_v = np.einsum("bvkl,bvl->bvk", A[:, :, :3, :3], verts) + A[:, :, :3, 3]
    if transl is not None:
        t = np.asarray(transl, dtype=np.float64).reshape(-1, 1, 3)
        out_v = out_v + t
        posed_joints = posed_joints + t
    if single:
        return LBSOutput(out_v[0], posed_joints[0], skin[0])
    return LBSOutput(out_v, posed_joints, skin)
