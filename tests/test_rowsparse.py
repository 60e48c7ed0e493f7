"""Row-sparse gathers and Adam (omnire.rowsparse) and instance segments (omnire.nodes.actors)
against obvious dense implementations."""
import pytest
import torch

from omnire.nodes.actors import instance_offsets, segment_rows
from omnire.rowsparse import gather_rows, row_runs, sparse_adam_step


def test_gather_rows_gradient_is_the_dense_gradient_made_sparse():
    torch.manual_seed(0)
    dense = torch.randn(12, 4, 3, dtype=torch.float64, requires_grad=True)
    sparse = dense.detach().clone().requires_grad_(True)
    rows = torch.tensor([1, 2, 3, 7, 8, 11])
    w = torch.randn(6, 4, 3, dtype=torch.float64)
    (dense[rows] * w).sum().backward()
    out = gather_rows(sparse, rows)
    torch.testing.assert_close(out, dense[rows])
    (out * w).sum().backward()
    assert sparse.grad.layout == torch.sparse_coo
    torch.testing.assert_close(sparse.grad.to_dense(), dense.grad)
    with torch.no_grad():  # outside autograd: a plain gather
        assert gather_rows(sparse, rows).grad_fn is None


def test_row_runs():
    assert row_runs(torch.tensor([3, 4, 5, 9, 10, 12])) == ([3, 9, 12], [3, 2, 1])
    assert row_runs(torch.tensor([], dtype=torch.long)) == ([], [])


def reference_adam(p, grads_per_step, lr, betas=(0.9, 0.999), eps=1e-15):
    """Textbook Adam in float64 on rows that receive a gradient every step."""
    m, v = torch.zeros_like(p), torch.zeros_like(p)
    for t, g in enumerate(grads_per_step, start=1):
        m = betas[0] * m + (1 - betas[0]) * g
        v = betas[1] * v + (1 - betas[1]) * g * g
        p = p - lr * (m / (1 - betas[0] ** t)) / ((v / (1 - betas[1] ** t)).sqrt() + eps)
    return p, m, v


@pytest.mark.parametrize("fused", [True, False])
def test_sparse_adam_steps_touched_rows_like_adam_and_leaves_the_rest(fused):
    torch.manual_seed(1)
    N, rows = 20, torch.tensor([2, 3, 4, 5, 9, 10, 17])
    param = torch.randn(N, 3)
    start = param.clone()
    group = {"lr": 0.05, "betas": (0.9, 0.999), "eps": 1e-15, "weight_decay": 0.0, "maximize": False, "fused": fused}
    state: dict = {}
    grads = [torch.randn(len(rows), 3) for _ in range(4)]
    for g in grads:
        sparse = torch.sparse_coo_tensor(rows[None], g, param.shape, is_coalesced=True, check_invariants=True)
        sparse_adam_step(param, sparse, state, group)
    expect, m, v = reference_adam(start[rows].double(), [g.double() for g in grads], group["lr"])
    torch.testing.assert_close(param[rows].double(), expect, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(state["exp_avg"][rows].double(), m, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(state["exp_avg_sq"][rows].double(), v, rtol=1e-5, atol=1e-9)
    others = torch.ones(N, dtype=torch.bool)
    others[rows] = False
    assert torch.equal(param[others], start[others])
    assert (state["exp_avg"][others] == 0).all() and (state["exp_avg_sq"][others] == 0).all()
    assert float(state["step"]) == 4


def test_sparse_adam_rejects_a_dense_gradient():
    with pytest.raises(ValueError, match="sparse COO"):
        sparse_adam_step(torch.zeros(3, 2), torch.zeros(3, 2), {}, {"fused": False})


def test_segment_rows_match_a_mask_over_every_row():
    g = torch.Generator().manual_seed(2)
    num_instances = 30
    counts = torch.randint(0, 6, (num_instances,), generator=g)  # some instances own no rows
    instance = torch.repeat_interleave(torch.arange(num_instances), counts)
    offsets = instance_offsets(instance, num_instances)
    for _ in range(20):
        ids = torch.nonzero(torch.rand(num_instances, generator=g) < 0.3).flatten()
        mask = torch.zeros(num_instances, dtype=torch.bool)
        mask[ids] = True
        torch.testing.assert_close(segment_rows(offsets, ids), torch.nonzero(mask[instance]).flatten())
    assert len(segment_rows(offsets, torch.zeros(0, dtype=torch.long))) == 0


def test_instance_offsets_refuse_interleaved_rows():
    with pytest.raises(ValueError, match="non-decreasing"):
        instance_offsets(torch.tensor([0, 1, 0]), 2)


def test_sparse_adam_sums_rows_gathered_twice():
    param = torch.zeros(6, 2, requires_grad=True)
    rows = torch.tensor([1, 2, 4])
    (gather_rows(param, rows).sum() + 2 * gather_rows(param, rows[1:]).sum()).backward()
    expect = torch.zeros(6, 2)
    expect[1], expect[2], expect[4] = 1, 3, 3
    state: dict = {}
    group = {"lr": 0.1, "betas": (0.9, 0.999), "eps": 1e-15, "weight_decay": 0.0, "maximize": False, "fused": False}
    with torch.no_grad():
        sparse_adam_step(param, param.grad, state, group)
    torch.testing.assert_close(state["exp_avg"], 0.1 * expect)


def test_step_sparse_params_shares_runs_only_between_gradients_of_the_same_rows():
    """Two parameters gathered with one row tensor (a node's), one with other rows and one
    gathered twice (coalesced): one optimiser step equals the textbook update of each."""
    from omnire.rowsparse import step_sparse_params

    torch.manual_seed(3)
    a, b, c, d = (torch.randn(12, k, requires_grad=True) for k in (3, 4, 2, 1))
    starts = [p.detach().clone() for p in (a, b, c, d)]
    shared, other = torch.tensor([0, 1, 2, 6, 7, 11]), torch.tensor([3, 4, 5, 8, 9, 10])  # same length
    loss = (gather_rows(a, shared) ** 2).sum() + (gather_rows(b, shared) ** 3).sum() + (gather_rows(c, other) ** 2).sum()
    loss = loss + gather_rows(d, other).sum() + gather_rows(d, other[1:]).sum()
    loss.backward()
    dense = [p.grad.to_dense() for p in (a, b, c, d)]
    opt = torch.optim.Adam([a, b, c, d], lr=0.1, eps=1e-15)
    step_sparse_params(opt)
    assert all(p.grad is None for p in (a, b, c, d))
    for p, start, g, rows in zip((a, b, c, d), starts, dense, (shared, shared, other, other)):
        expect, _, _ = reference_adam(start[rows].double(), [g[rows].double()], 0.1)
        torch.testing.assert_close(p.detach()[rows].double(), expect, rtol=1e-5, atol=1e-6)
        untouched = torch.ones(12, dtype=torch.bool)
        untouched[rows] = False
        assert torch.equal(p.detach()[untouched], start[untouched])
