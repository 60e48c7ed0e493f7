"""How much each Gaussian contributes to the training views, and which to keep.

A Gaussian's contribution to one view is its accumulated blending weight over the pixels,
sum_p w_i(p) with w_i(p) = alpha_i(p) T_i(p) (alpha_i its opacity times its footprint at
pixel p, T_i(p) the transmittance in front of it). Every rasterizer composites
rgb(p) = sum_i w_i(p) c_i, so with a one-channel colour c = 1 for every Gaussian,
d(sum_p rgb(p)) / d c_i = sum_p w_i(p) exactly: one forward and backward pass of *any*
rasterizer through autograd (:func:`view_weights`) gives every Gaussian's weight in that
view, including the rasterizer's own cut-offs (alpha < 1/255, the transmittance floor).
Tested against a per-pixel evaluation in float64 (tests/test_contribution.py).

A LiDAR sweep composites its rays' features the same way (features(r) = sum_i w_i(r) f_i,
``rasterize_lidar``), so :func:`sweep_weights` gives each Gaussian's weight summed over a
sweep's rays with the same trick, tested against a per-ray evaluation in float64. A run that
learns LiDAR ranks its Gaussians by both sensors (:func:`node_contributions`): a Gaussian
only the sweeps see (behind or beside forward-looking cameras) is not pruned for being
invisible to the cameras.

Two users: ``omnire compact`` prunes a trained run with it, and training prunes once at the end
of its growth phase when ``--method.densify.keep-after-growth`` is below 1 (:func:`prune_nodes`).
"""
from __future__ import annotations

import math
from typing import Callable, Optional, Sequence

import torch

from omnire.camera import Camera
from omnire.lidarprojection import may_reach
from omnire.lidarsweep import SensorPath, SweepRays, sectors_of
from omnire.rasterization import LidarRays, LidarSettings, RasterSettings, Splats


def _summed_weights(means: torch.Tensor, composite: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """(N,) d(sum of ``composite(ones)``) / d ones: each Gaussian's blending weight summed over
    what ``composite`` draws, given a one-channel colour (N, 1) of ones that requires grad."""
    N = means.shape[0]
    ones = torch.ones(N, 1, dtype=means.dtype, device=means.device, requires_grad=True)
    with torch.enable_grad():
        (grad,) = torch.autograd.grad(composite(ones).sum(), ones)
    return grad[:, 0].detach()


def view_weights(rasterizer, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                 opacities: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(N,) sum over the pixels of ``camera`` of each Gaussian's blending weight w_i = alpha_i T_i.

    Args: activated Gaussians as :class:`omnire.api.Splats` takes them: means (N, 3), quats
    (N, 4), scales (N, 3) (standard deviations), opacities (N,) in [0, 1]; no gradient flows
    to them. ``rasterizer``: any backend of the rasterizer contract (omnire/rasterization.py).
    """
    if means.shape[0] == 0:
        return torch.zeros(0, device=means.device)
    g = [t.detach() for t in (means, quats, scales, opacities)]
    return _summed_weights(means, lambda ones: rasterizer.rasterize(Splats(*g, ones), camera,
                                                                    RasterSettings(background=None)).rgb)


def sweep_weights(rasterizer, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                  opacities: torch.Tensor, rays: LidarRays, settings: Optional[LidarSettings] = None) -> torch.Tensor:
    """(N,) sum over the R rays of ``rays`` of each Gaussian's blending weight w_i = alpha_i T_i.

    Args as :func:`view_weights`; ``rasterizer`` needs the ``lidar`` capability
    (``rasterize_lidar``, omnire/rasterization.py)."""
    if means.shape[0] == 0 or len(rays) == 0:
        return torch.zeros(means.shape[0], device=means.device)
    g = [t.detach() for t in (means, quats, scales, opacities)]
    settings = LidarSettings() if settings is None else settings
    return _summed_weights(means, lambda ones: rasterizer.rasterize_lidar(Splats(*g, ones), rays, settings).features)


def _add(totals: dict[str, torch.Tensor], w: torch.Tensor, slices) -> None:
    """Add the (N,) weights ``w`` of a gathered set to the node rows its ``slices`` name."""
    for sl in slices:
        part = w[sl.start:sl.end].to(torch.float64)
        if sl.rows is None:
            totals[sl.node][: len(part)] += part
        else:
            totals[sl.node].index_add_(0, sl.rows, part)


@torch.no_grad()
def node_contributions(recon, views, progress: Optional[Callable[[], None]] = None,
                       sweeps: Sequence[SweepRays] = (), path: Optional[SensorPath] = None,
                       sectors: int = 1) -> dict[str, torch.Tensor]:
    """Per Gaussian node of ``recon`` (an :class:`omnire.api.Reconstruction`), the (N_node,)
    contribution of each of its Gaussians: its blending weight summed over ``views``
    (recorded cameras at their moments; actors count in the views where they are present,
    the only ones that draw them). The Gaussians are those the scene graph renders at each
    view (posed actors, deformed bodies, the camera's refined pose), culled to the view as a
    render culls them.

    With ``sweeps`` (recorded LiDAR sweeps, cast from ``path`` in ``sectors`` time sectors as
    :meth:`omnire.api.Reconstruction.render_sweep` renders them), the weight summed over
    their rays is added, each sensor as a share of its samples: camera weight / pixels of
    ``views`` + LiDAR weight / rays of ``sweeps``, so neither sensor outweighs the other by
    its sample count. ``progress`` is called after each view and each sweep."""
    nodes = recon.gaussian_nodes()
    camera = {name: torch.zeros(node.num_gaussians, dtype=torch.float64, device=recon.device)
              for name, node in nodes.items()}
    pixels = 0
    for view in views:
        cam = recon.camera(view)
        pixels += cam.width * cam.height
        g, slices, _ = recon.gather(cam, recon.time(view.frame))
        if g is not None and len(g):
            _add(camera, view_weights(recon.rasterizer, g.means, g.quats, g.activated_scales,
                                      g.activated_opacities, cam), slices)
        if progress is not None:
            progress()
    if not sweeps:
        return camera
    if path is None:
        raise ValueError("node_contributions: sweeps given without the sensor path they are cast from")
    lidar = {name: torch.zeros_like(t) for name, t in camera.items()}
    rays_total = 0
    settings = LidarSettings()
    for sweep in sweeps:
        rays_total += len(sweep)
        for sector in sectors_of(sweep, path, sectors, recon.device):
            g, slices, _ = recon.gather(None, recon.sweep_actor_moment(sweep, sector.time))
            if g is None or not len(g):
                continue
            # only the Gaussians that can reach the sector's rays (the others weigh 0 on them)
            reach = torch.nonzero(may_reach(g.means, g.scales, sector.rays, settings.eps_deg2))[:, 0]
            w = torch.zeros(len(g), dtype=g.means.dtype, device=g.means.device)
            w[reach] = sweep_weights(recon.rasterizer, g.means[reach], g.quats[reach], g.activated_scales[reach],
                                     g.activated_opacities[reach], sector.rays, settings)
            _add(lidar, w, slices)
        if progress is not None:
            progress()
    return {name: camera[name] / max(pixels, 1) + lidar[name] / max(rays_total, 1) for name in camera}


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
