"""How much each Gaussian contributes to the training views, and which to keep.

A Gaussian's contribution to one view is its accumulated blending weight over the pixels,
sum_p w_i(p) with w_i(p) = alpha_i(p) T_i(p) (alpha_i its opacity times its footprint at
pixel p, T_i(p) the transmittance in front of it). Every rasterizer composites
rgb(p) = sum_i w_i(p) c_i, so with a one-channel colour c = 1 for every Gaussian,
d(sum_p rgb(p)) / d c_i = sum_p w_i(p) exactly: one forward and backward pass of *any*
rasterizer through autograd (:func:`view_weights`) gives every Gaussian's weight in that
view, including the rasterizer's own cut-offs (alpha < 1/255, the transmittance floor).
Tested against a per-pixel evaluation in float64 (tests/test_contribution.py).

Two users: ``omnire compact`` prunes a trained run with it, and training prunes once at the end
of its growth phase when ``--method.densify.keep-after-growth`` is below 1 (:func:`prune_nodes`).
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch

from omnire.camera import Camera
from omnire.rasterization import RasterSettings, Splats


def view_weights(rasterizer, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                 opacities: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(N,) sum over the pixels of ``camera`` of each Gaussian's blending weight w_i = alpha_i T_i.

    Args: activated Gaussians as :class:`omnire.api.Splats` takes them: means (N, 3), quats
    (N, 4), scales (N, 3) (standard deviations), opacities (N,) in [0, 1]; no gradient flows
    to them. ``rasterizer``: any backend of the rasterizer contract (omnire/rasterization.py).
    """
    N = means.shape[0]
    if N == 0:
        return torch.zeros(0, device=means.device)
    ones = torch.ones(N, 1, dtype=means.dtype, device=means.device, requires_grad=True)
    with torch.enable_grad():
        out = rasterizer.rasterize(Splats(means.detach(), quats.detach(), scales.detach(), opacities.detach(), ones),
                                   camera, RasterSettings(background=None))
        (grad,) = torch.autograd.grad(out.rgb.sum(), ones)
    return grad[:, 0].detach()


@torch.no_grad()
def node_contributions(recon, views, progress: Optional[Callable[[], None]] = None) -> dict[str, torch.Tensor]:
    """Per Gaussian node of ``recon`` (an :class:`omnire.api.Reconstruction`), the (N_node,)
    summed blending weight of each of its Gaussians over ``views`` (recorded cameras at their
    moments; actors count in the views where they are present, the only ones that draw them).
    The Gaussians are those the scene graph renders at each view (posed actors, deformed
    bodies, the camera's refined pose), culled to the view as a render culls them."""
    totals = {name: torch.zeros(node.num_gaussians, dtype=torch.float64, device=recon.device)
              for name, node in recon.gaussian_nodes().items()}
    for view in views:
        camera = recon.camera(view)
        g, slices, _ = recon.gather(camera, recon.time(view.frame))
        if g is not None and len(g):
            w = view_weights(recon.rasterizer, g.means, g.quats, g.activated_scales, g.activated_opacities, camera)
            for sl in slices:
                part = w[sl.start:sl.end].to(torch.float64)
                if sl.rows is None:
                    totals[sl.node][: len(part)] += part
                else:
                    totals[sl.node].index_add_(0, sl.rows, part)
        if progress is not None:
            progress()
    return totals


def keep_top(contribution: torch.Tensor, fraction: float, groups: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(N,) bool: the ceil(``fraction`` x n) rows of largest ``contribution`` (N,) in each group
    of ``groups`` (N,) (e.g. the actor instance owning each Gaussian, so that an actor seen in
    few views keeps its share), or among all rows when ``groups`` is None. Ties are broken
    by row order (stable sort), so the result is deterministic."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction {fraction}: expected 0 < fraction <= 1")
    N = contribution.shape[0]
    keep = torch.zeros(N, dtype=torch.bool, device=contribution.device)
    if N == 0:
        return keep
    if groups is None:
        groups = torch.zeros(N, dtype=torch.long, device=contribution.device)
    if groups.shape != (N,):
        raise ValueError(f"groups: shape {tuple(groups.shape)}, expected ({N},)")
    # order rows by (group, contribution descending): rank within the group = position - group start
    by_value = torch.sort(contribution, descending=True, stable=True).indices
    order = by_value[torch.sort(groups[by_value], stable=True).indices]
    sorted_groups = groups[order]
    _, counts = torch.unique_consecutive(sorted_groups, return_counts=True)
    starts = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    quota = torch.repeat_interleave(torch.tensor([math.ceil(fraction * int(c)) for c in counts],
                                                 device=contribution.device), counts)
    rank = torch.arange(N, device=contribution.device) - starts
    keep[order[rank < quota]] = True
    return keep


@torch.no_grad()
def prune_nodes(trainer, contributions: dict[str, torch.Tensor], fraction: float) -> dict[str, tuple[int, int]]:
    """Keep, in every Gaussian node of ``trainer`` (an :class:`omnire.trainer.Trainer`), the
    ``fraction`` of its Gaussians with the largest ``contributions`` (per node, (N_node,)
    from :func:`node_contributions`); actor nodes keep that fraction of each instance (their
    ``instance`` buffer). Rows are cut by :meth:`omnire.trainer.Trainer.keep_gaussian_rows`,
    so training continues from the result. Returns {node: (count before, count after)}."""
    counts = {}
    for name, node in trainer.recon.gaussian_nodes().items():
        if node.num_gaussians == 0:
            counts[name] = (0, 0)
            continue
        keep = keep_top(contributions[name], fraction, node.gaussian_buffers.get("instance"))
        counts[name] = trainer.keep_gaussian_rows(name, keep)
    return counts
