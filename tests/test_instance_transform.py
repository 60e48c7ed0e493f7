"""Actor instances moved to the world (omnire.nodes.actors.transform_instances): the
segment-wise path against the per-row one (values and gradients, float64) and gradcheck."""
import dataclasses

import pytest
import torch

from omnire.gaussians import Gaussians
from omnire.geometry import axis_angle_to_rotmat, quat_left_matrix, quat_multiply, rotmat_to_quat
from omnire.nodes.actors import segment_lengths, transform_instances, transform_rows
from omnire.placement import _SegmentTransform


def local_gaussians(M: int, g: torch.Generator, dtype=torch.float64) -> Gaussians:
    z = torch.zeros(M, dtype=dtype)
    return Gaussians(torch.randn(M, 3, generator=g, dtype=dtype), torch.randn(M, 4, generator=g, dtype=dtype),
                     torch.zeros(M, 3, dtype=dtype), z, torch.zeros(M, 1, 3, dtype=dtype),
                     torch.zeros(M, 0, 3, dtype=dtype))


def test_quat_left_matrix_batches_like_quat_multiply():
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(5, 4, generator=g, dtype=torch.float64), torch.randn(5, 4, generator=g, dtype=torch.float64)
    torch.testing.assert_close((quat_left_matrix(a) @ b[..., None])[..., 0], quat_multiply(a, b))
    torch.testing.assert_close(quat_left_matrix(a[0]) @ b[0], quat_multiply(a[0], b[0]))


def test_segment_lengths_only_for_rows_grouped_in_id_order():
    ids = torch.tensor([1, 4, 7])
    assert segment_lengths(torch.tensor([1, 1, 4, 7, 7, 7]), ids) == [2, 1, 3]
    assert segment_lengths(torch.tensor([1, 7, 7]), ids) == [1, 0, 2]  # an instance without rows
    assert segment_lengths(torch.tensor([1, 4, 1]), ids) is None  # interleaved
    assert segment_lengths(torch.tensor([1, 2, 4]), ids) is None  # a row of an instance not in ids
    assert segment_lengths(torch.tensor([4, 7]), torch.tensor([7, 4])) is None  # ids not increasing
    assert segment_lengths(torch.tensor([4, 4]), torch.tensor([4, 4])) is None  # ids repeated


@pytest.mark.parametrize("instance", [[0, 0, 0, 2, 2, 5, 5, 5, 5], [2, 0, 5, 0, 2, 5, 5, 0, 5]],
                         ids=["grouped", "interleaved"])
def test_world_gaussians_and_gradients_match_the_per_row_path(instance):
    g = torch.Generator().manual_seed(1)
    instance = torch.tensor(instance)
    ids = torch.tensor([0, 2, 3, 5])  # instance 3 is present but has no rows
    local = local_gaussians(len(instance), g)
    rot = (0.7 * torch.randn(len(ids), 3, generator=g, dtype=torch.float64))
    t = torch.randn(len(ids), 3, generator=g, dtype=torch.float64)
    w_m, w_q = torch.randn(len(instance), 3, generator=g, dtype=torch.float64), \
        torch.randn(len(instance), 4, generator=g, dtype=torch.float64)
    results = []
    for fn in (transform_instances, transform_rows):
        leaves = [x.clone().requires_grad_(True) for x in (local.means, local.quats, rot, t)]
        out = fn(dataclasses.replace(local, means=leaves[0], quats=leaves[1]), instance, ids,
                 axis_angle_to_rotmat(leaves[2]), leaves[3])
        ((out.means * w_m).sum() + (out.quats * w_q).sum()).backward()
        results.append((out.means.detach(), out.quats.detach(), *[x.grad for x in leaves]))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    # and the world pose really is applied: row 0 belongs to instance 0 (slot 0)
    R0 = axis_angle_to_rotmat(rot[0])
    row0 = int(torch.nonzero(instance == 0)[0])
    torch.testing.assert_close(results[0][0][row0], R0 @ local.means[row0] + t[0])
    torch.testing.assert_close(results[0][1][row0], quat_multiply(rotmat_to_quat(R0), local.quats[row0]))


def test_segment_transform_gradcheck():
    g = torch.Generator().manual_seed(2)
    lengths = [3, 0, 2, 4]
    M, P = sum(lengths), len(lengths)
    args = [torch.randn(M, 3, generator=g, dtype=torch.float64), torch.randn(M, 4, generator=g, dtype=torch.float64),
            torch.randn(P, 3, 3, generator=g, dtype=torch.float64), torch.randn(P, 3, generator=g, dtype=torch.float64),
            torch.randn(P, 4, 4, generator=g, dtype=torch.float64)]
    args = [a.requires_grad_(True) for a in args]
    assert torch.autograd.gradcheck(lambda *a: _SegmentTransform.apply(*a, lengths), args)
