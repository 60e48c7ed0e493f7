"""Optimisers and learning-rate schedules.

One Adam per node, one parameter group per :class:`~omnire.nodes.base.ParamGroup`. Groups of
per-Gaussian parameters carry their ``key`` so the densification strategy can resize the
parameter and its Adam moments together.

Adam runs fused (one pass over parameter, gradient and moments; torch >= 2.4 on CPU and
CUDA) where the build supports it: on 300k Gaussians it steps in 12 ms instead of 46 ms
(foreach). A row-selective Adam (only the rows rendered this step, as gsplat's
SelectiveAdam) was measured and dropped on the CPU: gathering and scattering the rows cost
44-106 ms for 30-90% of 300k rows, more than the fused dense step over all of them.

Parameters whose gradient arrives sparse (actor nodes gather the rows of the instances
present at the rendered frame with :func:`omnire.rowsparse.gather_rows`) step only those
rows (:func:`omnire.rowsparse.step_sparse_params`), so actors absent from a frame cost
nothing in the optimiser either.
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch

from omnire.nodes.base import Node, ParamGroup
from omnire.rowsparse import step_sparse_params


def exponential_lr(lr: float, lr_final: Optional[float], step: int, max_steps: int, warmup_steps: int = 0) -> float:
    """Log-linear decay from ``lr`` to ``lr_final`` over ``max_steps`` (constant if
    ``lr_final`` is None), with optional linear warm-up from 0."""
    if lr_final is None or max_steps <= 0:
        value = lr
    else:
        t = min(max(step / max_steps, 0.0), 1.0)
        value = math.exp((1 - t) * math.log(lr) + t * math.log(max(lr_final, 1e-30)))
    if warmup_steps > 0 and step < warmup_steps:
        value *= step / warmup_steps
    return value


class Optimizers:
    """Adam per node. ``step(step)`` applies the schedules at schedule step ``step`` (the
    training step for a step budget; :mod:`omnire.schedule`) then steps every optimiser;
    ``max_steps`` is the schedule's length, over which the learning rates decay."""

    def __init__(self, nodes: dict[str, Node], max_steps: int) -> None:
        self.max_steps = max_steps
        self.groups: dict[str, list[ParamGroup]] = {}
        self.optimizers: dict[str, torch.optim.Adam] = {}
        for name, node in nodes.items():
            self.add_node(name, node)

    def add_node(self, name: str, node: Node) -> None:
        groups = [g for g in node.param_groups() if g.params]
        if not groups:
            return
        self.groups[name] = groups
        param_groups = [{"params": g.params, "lr": g.lr, "name": g.name} for g in groups]
        try:
            self.optimizers[name] = torch.optim.Adam(param_groups, eps=1e-15, fused=True)
        except (RuntimeError, TypeError, ValueError):  # no fused kernel for this device / build
            self.optimizers[name] = torch.optim.Adam(param_groups, eps=1e-15)

    def zero_grad(self) -> None:
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)

    def step(self, step: int) -> None:
        for name, opt in self.optimizers.items():
            for spec, group in zip(self.groups[name], opt.param_groups):
                group["lr"] = exponential_lr(spec.lr, spec.lr_final, step, self.max_steps, spec.warmup_steps)
            step_sparse_params(opt)  # row-sparse gradients first; clears them so opt.step() skips them
            opt.step()

    def learning_rates(self) -> dict[str, float]:
        """The learning rate of every group, ``{"<node>.<group>": lr}``, as the last
        :meth:`step` set it (the initial ones before any step)."""
        return {f"{name}.{group['name']}": float(group["lr"])
                for name, opt in self.optimizers.items() for group in opt.param_groups}

    def replace_gaussian_rows(
        self,
        name: str,
        node: Node,
        param_fn: Callable[[str, torch.Tensor], torch.Tensor],
        state_fn: Callable[[str, torch.Tensor], torch.Tensor],
    ) -> None:
        """Resize every per-Gaussian tensor of ``node`` with ``param_fn(key, old) -> new`` and
        its Adam moments with ``state_fn(key, old_moment) -> new_moment``; buffers too."""
        new = {k: param_fn(k, p.data) for k, p in node.gaussian_params.items()}
        new.update({k: param_fn(k, b) for k, b in node.gaussian_buffers.items()})
        old_params = {k: node.gaussian_params[k] for k in node.gaussian_params.keys()}
        node.set_gaussian_tensors(new)
        opt = self.optimizers.get(name)
        if opt is None:
            return
        by_key = {spec.key: i for i, spec in enumerate(self.groups[name]) if spec.key is not None}
        for key, gi in by_key.items():
            group = opt.param_groups[gi]
            old = old_params[key]
            state = opt.state.pop(old, {})
            new_p = node.gaussian_params[key]
            for s_name, value in list(state.items()):
                if s_name != "step" and torch.is_tensor(value) and value.shape == old.shape:
                    state[s_name] = state_fn(key, value)
            group["params"] = [new_p]
            self.groups[name][gi].params = [new_p]
            if state:
                opt.state[new_p] = state

    def state_dict(self) -> dict:
        return {name: opt.state_dict() for name, opt in self.optimizers.items()}

    def load_state_dict(self, state: dict) -> None:
        for name, opt in self.optimizers.items():
            opt.load_state_dict(state[name])
