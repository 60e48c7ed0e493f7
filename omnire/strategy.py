"""Densification with absolute 2D gradients (AbsGrad), written once for every node.

Per Gaussian the strategy accumulates |dL/d means2d| summed over pixels (from the
rasterizer's ``absgrad2d``), scaled to normalised device units (x W/2, x H/2 as in
3DGS/gsplat), and how often it was visible. Every ``refine_every`` training steps, once the
schedule (:mod:`omnire.schedule`: the step count for a step budget, the clock's for a time
budget) is at ``refine_start``:

- grow (before ``refine_stop``): Gaussians whose mean accumulated gradient exceeds
  ``grad_threshold`` are cloned when small (max scale <= ``scale_threshold`` x scene
  radius) and split in two when large (samples from the Gaussian, scales / 1.6);
- prune: opacity < ``prune_opacity``, too large (> ``prune_scale`` x scene radius, after the
  first opacity reset, when there was one), non-finite, or flagged by the node
  (``Node.extra_prune_mask``);
- nodes that rely on a row order (``Node.row_order``) get their rows permuted back;
- every ``reset_every`` schedule steps opacities are clamped to 2 x ``prune_opacity``, only
  while growth is still on (a reset needs densification steps after it to recover).

``refine_every`` counts training steps, not schedule steps: it is how many views the
statistics average over. A slow machine on a time budget, whose steps each stand for several
schedule steps, refines as often per view as a fast one, from statistics as good, instead
of growing from a handful of views what it has too few steps left to optimise.

Growth stops at ``refine_stop`` or at ``grow_fraction`` (half) of the schedule, whichever is
first: the reference stops at 15k of 30k steps, and shorter CPU runs keep that proportion
(a 3000-step run grows until 1500 and never resets opacity in its last steps; a time budget
grows for half its seconds).

State is explicit (tensors per node) and saved in checkpoints.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

import torch

from omnire.errors import ConfigError
from omnire.geometry import quat_to_rotmat
from omnire.nodes.base import Node
from omnire.optim import Optimizers
from omnire.schedule import passed


@dataclasses.dataclass
class DensifyConfig:
    """AbsGrad densification settings (defaults: docs/paper.md "Optimisation")."""

    grad_threshold: float = 3e-4
    """Mean normalised absolute 2D gradient above which a Gaussian grows."""
    scale_threshold: float = 3e-3
    """x scene radius: larger Gaussians are split, smaller cloned."""
    refine_start: int = 500
    """First step that refines."""
    refine_every: int = 100
    """Training steps between refinements (the views the statistics average over)."""
    refine_stop: int = 15_000
    """No growth after this step."""
    grow_fraction: float = 0.5
    """No growth after this fraction of the schedule either (the reference: 15k of 30k)."""
    reset_every: int = 3000
    """Opacity reset period (0 = never)."""
    prune_opacity: float = 0.005
    """Prune below this opacity."""
    prune_scale: float = 0.1
    """x scene radius: prune larger Gaussians (after the first opacity reset)."""
    max_gaussians: int = 200_000
    """Budget per node: growth stops adding above it (the largest gradients win). Sized for
    a CPU: at 400k the demo cut grew 824k Gaussians by half of a 600 s budget and took 3195
    steps in it against 4038 at 200k (docs/benchmarks.md); raise it for long runs on a GPU."""
    keep_after_growth: float = 0.4
    """When growth stops, keep this fraction of each node's Gaussians (of each actor's, for
    actor nodes): those contributing most to the training views and, when LiDAR is learned,
    the training sweeps (``Trainer.training_contributions``); the remaining steps are then
    shorter. 1 = keep all."""

    def __post_init__(self) -> None:
        if not 0 < self.grow_fraction <= 1:
            raise ConfigError(f"densify.grow_fraction: {self.grow_fraction}, expected a fraction of the schedule in (0, 1]")
        if not 0 < self.keep_after_growth <= 1:
            raise ConfigError(f"densify.keep_after_growth: {self.keep_after_growth}, expected a fraction in (0, 1]")


@dataclasses.dataclass
class NodeSlice:
    """Which rendered rows belong to a node: rendered[start:end] <- node rows ``rows``
    (None = all rows in order)."""

    node: str
    start: int
    end: int
    rows: Optional[torch.Tensor]


class AbsGradStrategy:
    """AbsGrad densification of every Gaussian node; ``max_steps``: the schedule's length
    (growth stops at half of it at the latest)."""

    def __init__(self, config: DensifyConfig, scene_radius: float, max_steps: Optional[int] = None) -> None:
        self.config = config
        self.scene_radius = scene_radius
        self.refine_stop = (config.refine_stop if max_steps is None
                            else min(config.refine_stop, int(max_steps * config.grow_fraction)))
        self.state: dict[str, dict[str, torch.Tensor]] = {}

    def _node_state(self, name: str, node: Node) -> dict[str, torch.Tensor]:
        st = self.state.get(name)
        n = node.num_gaussians
        if st is None or st["grad2d"].shape[0] != n:
            dev = node.gaussian_params["means"].device
            st = {"grad2d": torch.zeros(n, device=dev), "count": torch.zeros(n, device=dev)}
            self.state[name] = st
        return st

    @torch.no_grad()
    def accumulate(self, nodes: dict[str, Node], slices: list[NodeSlice], absgrad2d: torch.Tensor,
                   radii: torch.Tensor, width: int, height: int) -> None:
        """Add one rendered view's AbsGrad (M,2) and radii (M,) to the per-node statistics."""
        # |(g_x w / 2, g_y h / 2)|; hypot of the two columns is one elementwise pass where
        # norm(dim=-1) reduces over a length-2 axis (2.5x slower on the CPU at 350k rows)
        norms = torch.hypot(absgrad2d[:, 0] * (width / 2.0), absgrad2d[:, 1] * (height / 2.0))
        visible = radii > 0
        for sl in slices:
            node = nodes[sl.node]
            if node.num_gaussians == 0:
                continue
            st = self._node_state(sl.node, node)
            g, v = norms[sl.start : sl.end], visible[sl.start : sl.end].float()
            if sl.rows is None:
                st["grad2d"] += g * v
                st["count"] += v
            else:
                st["grad2d"].index_add_(0, sl.rows, g * v)
                st["count"].index_add_(0, sl.rows, v)

    def step(self, nodes: dict[str, Node], optimizers: Optimizers, step: int, schedule_step: Optional[int] = None,
             since: Optional[int] = None) -> dict[str, int]:
        """After training step ``step``: refine every ``refine_every`` training steps (the
        statistics of as many views each time) while the schedule, at ``schedule_step``
        (default ``step``), is past ``refine_start`` (growth only before the stop); reset
        opacities where the schedule passed a multiple of ``reset_every`` going from schedule
        step ``since`` (default ``schedule_step - 1``) to ``schedule_step``
        (:func:`omnire.schedule.passed`). Returns counts of what was done."""
        c = self.config
        at = step if schedule_step is None else schedule_step
        since = at - 1 if since is None else since
        report = {"grown": 0, "pruned": 0}
        if at >= c.refine_start and step % c.refine_every == 0 and step > 0:
            for name, node in nodes.items():
                if node.num_gaussians == 0 or name not in self.state:
                    continue
                if at < self.refine_stop:
                    report["grown"] += self._grow(name, node, optimizers)
                report["pruned"] += self._prune(name, node, optimizers, at)
                self.rows_changed(name, node, optimizers)
        if 0 < at < self.refine_stop and passed(c.reset_every, since, at):
            for name, node in nodes.items():
                if node.num_gaussians:
                    self._reset_opacity(name, node, optimizers)
        return report

    def rows_changed(self, name: str, node: Node, optimizers: Optimizers) -> None:
        """After rows of node ``name`` were added or removed: put its rows back in the order
        the node relies on (:meth:`~omnire.nodes.base.Node.row_order`, e.g. actor nodes keep
        each instance's rows contiguous), tensors and Adam moments alike, and drop its
        densification statistics, which described the old rows."""
        order = node.row_order()
        if order is not None:
            optimizers.replace_gaussian_rows(name, node, lambda k, t: t[order], lambda k, s: s[order])
        self.state.pop(name, None)

    @torch.no_grad()
    def _grow(self, name: str, node: Node, optimizers: Optimizers) -> int:
        c = self.config
        st = self.state[name]
        avg = st["grad2d"] / st["count"].clamp_min(1)
        high = avg > c.grad_threshold
        room = c.max_gaussians - node.num_gaussians
        if room <= 0:
            return 0
        if int(high.sum()) > room:
            keep = torch.topk(torch.where(high, avg, torch.zeros_like(avg)), room).indices
            high = torch.zeros_like(high)
            high[keep] = True
        max_scale = torch.exp(node.gaussian_params["scales"].max(dim=-1).values)
        small = max_scale <= c.scale_threshold * self.scene_radius
        clone, split = high & small, high & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            _duplicate(name, node, optimizers, clone)
        if n_split:
            split = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=split.device)])
            _split(name, node, optimizers, split)
        return n_clone + n_split

    @torch.no_grad()
    def _prune(self, name: str, node: Node, optimizers: Optimizers, step: int) -> int:
        c = self.config
        p = node.gaussian_params
        prune = torch.sigmoid(p["opacities"]) < c.prune_opacity
        # size pruning only once an opacity reset has happened (the first is at reset_every,
        # if growth is still on then): without one, large Gaussians that stand for the sky
        # and far surfaces would be cut from a fitted scene with no steps to regrow them
        if c.reset_every > 0 and c.reset_every < self.refine_stop and step > c.reset_every:
            prune |= torch.exp(p["scales"]).max(dim=-1).values > c.prune_scale * self.scene_radius
        for k in p.keys():
            prune |= ~torch.isfinite(p[k].reshape(p[k].shape[0], -1)).all(dim=1)
        extra = node.extra_prune_mask()
        if extra is not None:
            prune |= extra
        n = int(prune.sum())
        if n:
            keep = ~prune
            optimizers.replace_gaussian_rows(name, node, lambda k, t: t[keep], lambda k, s: s[keep])
        return n

    @torch.no_grad()
    def _reset_opacity(self, name: str, node: Node, optimizers: Optimizers) -> None:
        limit = math.log(2 * self.config.prune_opacity / (1 - 2 * self.config.prune_opacity))

        def param_fn(k, t):
            return torch.clamp_max(t, limit) if k == "opacities" else t

        def state_fn(k, s):
            return torch.zeros_like(s) if k == "opacities" else s

        optimizers.replace_gaussian_rows(name, node, param_fn, state_fn)

    def state_dict(self) -> dict:
        return {"state": {k: {n: t.clone() for n, t in v.items()} for k, v in self.state.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.state = {k: dict(v) for k, v in state["state"].items()}


def _append_zeros(s: torch.Tensor, n: int) -> torch.Tensor:
    return torch.cat([s, s.new_zeros((n, *s.shape[1:]))])


def _duplicate(name: str, node: Node, optimizers: Optimizers, mask: torch.Tensor) -> None:
    n = int(mask.sum())
    optimizers.replace_gaussian_rows(
        name, node, lambda k, t: torch.cat([t, t[mask]]), lambda k, s: _append_zeros(s, n)
    )


def _split(name: str, node: Node, optimizers: Optimizers, mask: torch.Tensor) -> None:
    """Replace each selected Gaussian by two samples from it with scales / 1.6."""
    p = node.gaussian_params
    n = int(mask.sum())
    scales = torch.exp(p["scales"][mask])  # (n, 3)
    R = quat_to_rotmat(p["quats"][mask])  # (n, 3, 3)
    samples = torch.randn(2, n, 3, device=scales.device) * scales
    offsets = torch.einsum("nij,bnj->bni", R, samples).reshape(2 * n, 3)
    keep = ~mask

    def param_fn(k, t):
        sel = t[mask]
        rep = sel.repeat(2, *([1] * (t.ndim - 1)))
        if k == "means":
            rep = rep + offsets
        elif k == "scales":
            rep = rep - math.log(1.6)
        return torch.cat([t[keep], rep])

    optimizers.replace_gaussian_rows(name, node, param_fn, lambda k, s: _append_zeros(s[keep], 2 * n))
