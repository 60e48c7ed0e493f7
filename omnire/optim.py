"""Optimisers and learning-rate schedules.

One Adam per node, one parameter group per :class:`~omnire.nodes.base.ParamGroup`. Groups of
per-Gaussian parameters carry their ``key`` so the densification strategy can resize the
parameter and its Adam moments together.

Selective Adam (as gsplat's ``SelectiveAdam``): when a node rendered only some of its rows
this step (actor nodes render only the instances present at the frame), its per-Gaussian
parameters are updated on those rows only: moments and parameters of the other rows stay
as they are, so a step costs nothing for actors absent from the frame (dense Adam would
keep moving them on stale momentum, at O(all Gaussians) per step).
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch
from torch import nn

from omnire.nodes.base import Node, ParamGroup


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
    """Adam per node. ``step(step)`` applies the schedules then steps every optimiser."""

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
        self.optimizers[name] = torch.optim.Adam(
            [{"params": g.params, "lr": g.lr, "name": g.name} for g in groups], eps=1e-15
        )

    def zero_grad(self) -> None:
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)

    def step(self, step: int, rendered_rows: Optional[dict[str, Optional[torch.Tensor]]] = None) -> None:
        """Apply the schedules and step every optimiser. ``rendered_rows`` maps node name ->
        the rows of its per-Gaussian parameters rendered this step (None: all rows); those
        nodes' per-Gaussian parameters get a selective Adam step on these rows only."""
        for name, opt in self.optimizers.items():
            rows = (rendered_rows or {}).get(name)
            for spec, group in zip(self.groups[name], opt.param_groups):
                group["lr"] = exponential_lr(spec.lr, spec.lr_final, step, self.max_steps, spec.warmup_steps)
                if rows is not None and spec.key is not None:
                    for p in group["params"]:
                        if p.grad is not None:
                            selective_adam_step(p, rows, opt.state[p], group)
                            p.grad = None  # done: the dense step below skips it
            opt.step()

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


@torch.no_grad()
def selective_adam_step(param: torch.Tensor, rows: torch.Tensor, state: dict, group: dict) -> None:
    """One Adam step (torch.optim.Adam's arithmetic, no weight decay or amsgrad) on
    ``param[rows]`` only. ``param`` (N, ...) with ``.grad``; ``rows`` (M,) unique row indices;
    ``state`` the optimiser's state of ``param`` (``step``, ``exp_avg``, ``exp_avg_sq``,
    created if missing, the same layout as torch's Adam so checkpoints and densification treat
    both alike); ``group`` its param group (``lr``, ``betas``, ``eps``). The step counter is
    per parameter (bias correction as if every step had touched the row, as gsplat)."""
    if group.get("weight_decay", 0) or group.get("amsgrad", False) or group.get("maximize", False):
        raise ValueError("selective_adam_step: weight decay, amsgrad and maximize are not supported")
    if not state:
        state["step"] = torch.tensor(0.0)
        state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
        state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
    beta1, beta2 = group["betas"]
    lr, eps = float(group["lr"]), float(group["eps"])
    state["step"] += 1
    t = float(state["step"])
    g = param.grad[rows]
    m = state["exp_avg"][rows].lerp_(g, 1 - beta1)
    v = state["exp_avg_sq"][rows].mul_(beta2).addcmul_(g, g, value=1 - beta2)
    state["exp_avg"][rows] = m
    state["exp_avg_sq"][rows] = v
    bias1, bias2 = 1 - beta1 ** t, 1 - beta2 ** t
    denom = (v.sqrt() / math.sqrt(bias2)).add_(eps)
    param[rows] = param[rows].addcdiv(m, denom, value=-lr / bias1)


def count_parameters(modules: dict[str, nn.Module]) -> int:
    return sum(p.numel() for m in modules.values() for p in m.parameters())
