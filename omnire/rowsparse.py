"""Row-sparse training of per-Gaussian parameters: absent actors cost nothing.

An actor node renders only the Gaussians of the instances present at the frame. With a
plain gather (``param[rows]``) autograd still hands back a gradient of the full (N, ...)
shape, and Adam then steps every row, so each step costs O(N) for N Gaussians of the
node, present or not. Here:

- :func:`gather_rows` gathers rows (M,) and gives the parameter a *sparse* COO gradient
  (indices = the gathered rows, values (M, ...)): no (N, ...) tensor is touched;
- :func:`sparse_adam_step` steps only those rows. Nodes keep the rows of each instance
  contiguous, so the gathered rows form a few runs; Adam runs on views of those runs with
  the fused kernel (no gather or scatter of moments).

Semantics are those of lazy / sparse Adam (TensorFlow's LazyAdam, torch's SparseAdam):
rows without a gradient this step keep their moments and do not move, where dense Adam
would keep moving them with decaying momentum. Bias correction uses the parameter's step
count, as dense Adam does for every row.
"""
from __future__ import annotations

import itertools
from typing import Optional

import torch


class _GatherRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, param: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(rows)
        ctx.shape = param.shape
        return param.index_select(0, rows)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (rows,) = ctx.saved_tensors
        return row_sparse(rows, grad, ctx.shape), None


def row_sparse(rows: torch.Tensor, values: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """The gradient of a parameter of ``shape`` (N, ...) whose rows ``rows`` (M,), strictly
    increasing, got ``values`` (M, ...): a sparse COO tensor declared coalesced, the form
    :func:`step_sparse_params` steps row by row."""
    return torch.sparse_coo_tensor(rows[None], values.contiguous(), shape, is_coalesced=True, check_invariants=False)


def gather_rows(param: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``param[rows]`` (M, ...) whose gradient reaches ``param`` as a sparse COO tensor.

    ``rows`` (M,) long must be strictly increasing (the sparse gradient is declared
    coalesced); callers pass rows built from sorted instance segments.
    """
    if not (param.requires_grad and torch.is_grad_enabled()):
        return param.index_select(0, rows)
    return _GatherRows.apply(param, rows)


def row_runs(rows: torch.Tensor) -> tuple[list[int], list[int]]:
    """Maximal runs of consecutive values in increasing ``rows`` (M,): (first row of each
    run, its length), e.g. [3,4,5,9,10] -> ([3, 9], [3, 2])."""
    if len(rows) == 0:
        return [], []
    new_run = torch.ones(len(rows), dtype=torch.bool, device=rows.device)
    new_run[1:] = rows[1:] != rows[:-1] + 1
    starts = torch.nonzero(new_run).flatten()
    lengths = torch.diff(starts, append=torch.tensor([len(rows)], device=rows.device))
    return rows[starts].tolist(), lengths.tolist()


def init_adam_state(param: torch.Tensor, fused: bool) -> dict:
    """Adam state as ``torch.optim.Adam`` creates it (so checkpoints mix freely)."""
    step = torch.zeros((), dtype=torch.float32, device=param.device) if fused else torch.tensor(0.0)
    return {"step": step, "exp_avg": torch.zeros_like(param, memory_format=torch.preserve_format),
            "exp_avg_sq": torch.zeros_like(param, memory_format=torch.preserve_format)}


def _runs_key(rows: torch.Tensor) -> tuple[int, int, int, int]:
    """Identifies the memory ``rows`` (M,) occupies: the parameters one node gathered with one
    row tensor get sparse gradients whose indices share it."""
    return rows.untyped_storage().data_ptr(), rows.storage_offset(), rows.shape[0], rows.stride(0)


@torch.no_grad()
def sparse_adam_step(param: torch.Tensor, grad: torch.Tensor, state: dict, group: dict,
                     runs_cache: Optional[dict] = None) -> None:
    """One Adam step of the rows of ``param`` (N, ...) that ``grad`` (sparse COO, same
    shape) holds; ``state`` is the parameter's Adam state (created if empty), ``group`` its
    ``torch.optim.Adam`` parameter group (lr, betas, eps, weight_decay, fused, ...).
    ``runs_cache`` (a dict the caller keeps for the gradients of one backward pass) saves
    finding the row runs again for each parameter gathered with the same rows."""
    from torch.optim.adam import adam

    if grad.layout != torch.sparse_coo or grad.shape != param.shape:
        raise ValueError(f"sparse_adam_step: expected a sparse COO gradient of shape {tuple(param.shape)}, "
                         f"got {grad.layout} {tuple(grad.shape)}")
    # Autograd drops the "coalesced" flag when it stores the gradient; rows from
    # gather_rows are strictly increasing, which is all coalescing would ensure.
    rows, values = grad._indices()[0], grad._values()
    cached = runs_cache.get(_runs_key(rows)) if runs_cache is not None else None
    if cached is None:
        if len(rows) > 1 and not bool((rows[1:] > rows[:-1]).all()):  # e.g. gathered twice: sum duplicates
            grad = grad.coalesce()
            rows, values = grad.indices()[0], grad.values()
            cached = (None, *row_runs(rows))  # these rows are this gradient's own: not cached
        else:
            cached = (rows, *row_runs(rows))
            if runs_cache is not None:  # the entry holds ``rows``: their memory (the key) stays theirs
                runs_cache[_runs_key(rows)] = cached
    firsts, lengths = cached[1], cached[2]
    fused = bool(group.get("fused"))
    if not state:
        state.update(init_adam_state(param, fused))
    if not firsts:
        return
    offsets = list(itertools.accumulate(lengths[:-1], initial=0))  # where each run starts in ``values``
    views = [param.narrow(0, r, n) for r, n in zip(firsts, lengths)]
    grads = [values.narrow(0, o, n) for o, n in zip(offsets, lengths)]
    exp_avgs = [state["exp_avg"].narrow(0, r, n) for r, n in zip(firsts, lengths)]
    exp_avg_sqs = [state["exp_avg_sq"].narrow(0, r, n) for r, n in zip(firsts, lengths)]
    # one step counter per run (the kernel increments each); all equal the parameter's
    steps = [state["step"].clone() for _ in firsts]
    beta1, beta2 = group["betas"]
    adam(views, grads, exp_avgs, exp_avg_sqs, [], steps, foreach=False, fused=fused, capturable=False,
         differentiable=False, grad_scale=None, found_inf=None, has_complex=False, amsgrad=False,
         beta1=beta1, beta2=beta2, lr=group["lr"], weight_decay=group["weight_decay"], eps=group["eps"],
         maximize=group["maximize"])
    state["step"] += 1


def step_sparse_params(optimizer: torch.optim.Optimizer) -> None:
    """Step every parameter of ``optimizer`` whose gradient is sparse with
    :func:`sparse_adam_step` and clear that gradient, so the optimiser's own (dense) step
    skips it. A node's parameters share their rows: the row runs are found once for all."""
    runs_cache: dict = {}
    for group in optimizer.param_groups:
        for p in group["params"]:
            if p.grad is not None and p.grad.layout == torch.sparse_coo:
                sparse_adam_step(p, p.grad, optimizer.state[p], group, runs_cache)
                p.grad = None
