"""The native skinning kernel (csrc/skin.cpp) against the torch composition: same outputs,
float64 finite-difference gradients, every quaternion branch and its ties, any point
order, and clear errors for bad indices."""
from __future__ import annotations

import pytest
import torch

from omnire.geometry import axis_angle_to_rotmat
from omnire_smpl.skinning import native_skinning_available, skin_gaussians, skin_gaussians_torch

OK, REASON = native_skinning_available()
pytestmark = pytest.mark.skipif(not OK, reason=f"native skinning unavailable: {REASON}")


def _case(P=3, J=24, M=400, K=4, dtype=torch.float64, seed=0, sorted_slots=True):
    """Random bodies: A (P, J, 3, 4) rotations (some turned far, so every quaternion branch
    occurs) with translations; M points with K joints and weights summing to 1."""
    g = torch.Generator().manual_seed(seed)
    angles = torch.randn(P, J, 3, generator=g, dtype=dtype) * 1.8
    R = axis_angle_to_rotmat(angles)
    t = torch.randn(P, J, 3, 1, generator=g, dtype=dtype)
    A = torch.cat([R, t], -1)
    slot = torch.randint(P, (M,), generator=g)
    if sorted_slots:
        slot = slot.sort().values
    joints = torch.stack([torch.randperm(J, generator=g)[:K] for _ in range(M)])
    w = torch.rand(M, K, generator=g, dtype=dtype) ** 3  # often one dominant joint
    w = w / w.sum(1, keepdim=True)
    means = torch.randn(M, 3, generator=g, dtype=dtype)
    quats = torch.randn(M, 4, generator=g, dtype=dtype)
    return A, slot, joints, w, means, quats


def _branches(A, slot, joints, w):
    T = (w[..., None] * A.reshape(-1, 12)[slot[:, None] * A.shape[1] + joints]).sum(1).reshape(-1, 3, 4)
    m = T[:, :, :3]
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    d = torch.stack([m[:, 2, 2], m[:, 1, 1], m[:, 0, 0]], -1)
    return torch.where(tr > 0, 0, 3 - d.argmax(-1))


@pytest.mark.parametrize("sorted_slots", [True, False])
def test_native_matches_torch_forward_and_backward_float32(sorted_slots):
    A, slot, joints, w, means, quats = (x.float() if x.is_floating_point() else x
                                        for x in _case(sorted_slots=sorted_slots))
    assert set(_branches(A, slot, joints, w).tolist()) == {0, 1, 2, 3}
    outs, grads = [], []
    for native in (True, False):
        a, x, q = (v.clone().requires_grad_() for v in (A, means, quats))
        m_out, q_out = skin_gaussians(a, slot, joints, w, x, q, native=native)
        g = torch.Generator().manual_seed(5)
        loss = (m_out * torch.randn(m_out.shape, generator=g)).sum() + (q_out * torch.randn(q_out.shape, generator=g)).sum()
        loss.backward()
        outs.append((m_out.detach(), q_out.detach()))
        grads.append((a.grad, x.grad, q.grad))
    for u, v in zip(outs[0], outs[1]):
        torch.testing.assert_close(u, v, rtol=1e-5, atol=1e-5)
    for u, v in zip(grads[0], grads[1]):
        torch.testing.assert_close(u, v, rtol=1e-4, atol=1e-4)


def test_native_gradients_match_finite_differences_float64():
    A, slot, joints, w, means, quats = _case(P=2, J=5, M=40, K=3, seed=1, sorted_slots=False)
    assert set(_branches(A, slot, joints, w).tolist()) == {0, 1, 2, 3}

    def f(a, x, q):
        return skin_gaussians(a, slot, joints, w, x, q, native=True)

    inputs = tuple(v.clone().requires_grad_() for v in (A, means, quats))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_diagonal_ties_and_blends_of_opposite_rotations_match_torch():
    """Halfway between 180-degree turns about x and y the blend is diag(0, 0, -1): a tie of
    the two largest diagonal entries, which must pick the later axis (y) as torch does;
    weights that do not sum to 1 are not rotations at all and must still agree."""
    A = torch.zeros(1, 3, 3, 4, dtype=torch.float64)
    A[0, 0, :, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    A[0, 1, :, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    A[0, 2, :, :3] = axis_angle_to_rotmat(torch.tensor([0.3, -2.9, 0.4], dtype=torch.float64))
    A[0, :, :, 3] = torch.randn(3, 3, dtype=torch.float64)
    slot = torch.zeros(3, dtype=torch.long)
    joints = torch.tensor([[0, 1], [0, 2], [1, 2]])
    w = torch.tensor([[0.5, 0.5], [0.3, 0.2], [1.7, 0.9]], dtype=torch.float64)
    assert _branches(A, slot, joints, w)[0] == 2
    means = torch.randn(3, 3, dtype=torch.float64)
    quats = torch.randn(3, 4, dtype=torch.float64)
    res = []
    for native in (True, False):
        a, x, q = (v.clone().requires_grad_() for v in (A, means, quats))
        m_out, q_out = skin_gaussians(a, slot, joints, w, x, q, native=native)
        (m_out.sum() + (q_out * torch.arange(1.0, 5.0, dtype=torch.float64)).sum()).backward()
        res.append((m_out, q_out, a.grad, x.grad, q.grad))
    for u, v in zip(res[0], res[1]):
        torch.testing.assert_close(u, v, rtol=1e-12, atol=1e-12)


def test_torch_fallback_is_the_reference_composition():
    A, slot, joints, w, means, quats = _case(M=50)
    for u, v in zip(skin_gaussians(A, slot, joints, w, means, quats, native=False),
                    skin_gaussians_torch(A, slot, joints, w, means, quats)):
        assert torch.equal(u, v)


def test_bad_indices_and_dtypes_are_refused_with_the_field_named():
    A, slot, joints, w, means, quats = _case(M=10)
    with pytest.raises(RuntimeError, match="out of range"):
        skin_gaussians(A, slot + 5, joints, w, means, quats, native=True)
    with pytest.raises(RuntimeError, match="out of range"):
        skin_gaussians(A, slot, joints + 24, w, means, quats, native=True)
    with pytest.raises(ValueError, match="float32/float64"):
        skin_gaussians(A, slot, joints, w.float(), means, quats, native=True)
    empty = skin_gaussians(A, slot[:0], joints[:0], w[:0], means[:0], quats[:0], native=True)
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 4)
