"""Skinning of Gaussians: blended joint transforms move their means and turn their rotations.

:func:`skin_gaussians` is one native pass per direction (csrc/skin.cpp) on CPU float32 /
float64 tensors and the torch composition :func:`skin_gaussians_torch` otherwise (another
device, or the extension unavailable). Both give the same numbers up to float rounding
(tests/test_skinning.py); the native one saves the dozen per-point passes and autograd
nodes of the torch one, about 5 ms of a training step on the demo scene's 25k SMPL Gaussians.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from omnire.api import NativeExtension, quat_multiply, rotmat_to_quat
from omnire_smpl.lbs import blend_transforms

# No instruction-set flags: the kernel is a handful of multiply-adds per point and builds
# for any x86 or ARM CPU.
EXTENSION = NativeExtension("omnire_smpl_skin", [Path(__file__).parent / "csrc" / "skin.cpp"],
                            ("-O3", "-fopenmp", "-std=c++17"), ("-fopenmp",), purpose="SMPL skinning")
QUAT_EPS = 1e-8  # rotmat_to_quat's radicand floor


def skin_gaussians_torch(A: torch.Tensor, slot: torch.Tensor, joints: torch.Tensor, weights: torch.Tensor,
                         means: torch.Tensor, quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference composition of :func:`skin_gaussians` in torch ops."""
    T = blend_transforms(A, slot, joints, weights)  # (M, 3, 4)
    R = T[:, :, :3]
    moved = torch.einsum("mij,mj->mi", R, means) + T[:, :, 3]
    return moved, quat_multiply(rotmat_to_quat(R, QUAT_EPS), quats)


class _SkinFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, A, slot, joints, weights, means, quats, nthreads):
        ctx.nthreads = nthreads
        ctx.save_for_backward(A, slot, joints, weights, means, quats)
        moved, turned = EXTENSION.module().skin_forward(A, slot, joints, weights, means, quats, QUAT_EPS, nthreads)
        return moved, turned

    @staticmethod
    def backward(ctx, g_means, g_quats):
        A, slot, joints, weights, means, quats = ctx.saved_tensors
        g_means = torch.zeros_like(means) if g_means is None else g_means.contiguous()
        g_quats = torch.zeros_like(quats) if g_quats is None else g_quats.contiguous()
        gA, gx, gq = EXTENSION.module().skin_backward(A, slot, joints, weights, means, quats, g_means, g_quats,
                                                      QUAT_EPS, ctx.nthreads)
        return gA, None, None, None, gx, gq, None


def load_extension():
    """``(module, "")`` or ``(None, reason)``; builds at most once per process."""
    return EXTENSION.load()


def native_skinning_available() -> tuple[bool, str]:
    mod, reason = load_extension()
    return mod is not None, reason


def skin_gaussians(A: torch.Tensor, slot: torch.Tensor, joints: torch.Tensor, weights: torch.Tensor,
                   means: torch.Tensor, quats: torch.Tensor, native: Optional[bool] = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Skinned means and rotations of M Gaussians.

    Args:
        A: (P, J, 3, 4) joint transforms of P bodies (rotation | translation).
        slot: (M,) int64 body of each Gaussian, in [0, P).
        joints: (M, K) int64 joint indices and weights (M, K) their skinning weights (no
            gradient; each row sums to 1 for a rigid motion, not required here).
        means: (M, 3) and quats (M, 4) wxyz, not necessarily unit (the product is linear in them).
        native: force (True) or forbid (False) the native kernel; None: native when it applies.
    Returns:
        means (M, 3) ``R_i x + t_i`` and quats (M, 4) ``quat(R_i) (x) q`` with
        ``[R_i | t_i] = sum_k w_ik A[slot_i, j_ik]`` and ``quat`` as
        :func:`omnire.geometry.rotmat_to_quat` (w >= 0).
    """
    applies = (A.device.type == "cpu" and A.dtype in (torch.float32, torch.float64)
               and all(t.device.type == "cpu" and t.dtype == A.dtype for t in (weights, means, quats))
               and not weights.requires_grad)
    if native is None:
        native = applies and native_skinning_available()[0]
    if not native:
        return skin_gaussians_torch(A, slot, joints, weights, means, quats)
    if not applies:
        raise ValueError("skin_gaussians(native=True): CPU float32/float64 tensors of one dtype and weights "
                         f"without gradient expected, got A {A.dtype} on {A.device}")
    return _SkinFn.apply(A.contiguous(), slot.contiguous(), joints.contiguous(), weights.contiguous(),
                         means.contiguous(), quats.contiguous(), torch.get_num_threads())
