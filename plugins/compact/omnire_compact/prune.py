"""Pruning a trainer's scene graph to the Gaussians that contribute most, node by node."""
from __future__ import annotations

import torch

from omnire_compact.contribution import keep_top


@torch.no_grad()
def prune_nodes(trainer, contributions: dict[str, torch.Tensor], fraction: float) -> dict[str, tuple[int, int]]:
    """Keep, in every Gaussian node of ``trainer`` (an :class:`omnire.api.Trainer`), the
    ``fraction`` of its Gaussians with the largest ``contributions`` (per node, (N_node,)
    from :func:`~omnire_compact.contribution.node_contributions`); actor nodes keep that
    fraction of each instance (their ``instance`` buffer). Parameters, buffers and Adam
    moments are cut together, so training can continue from the result. Returns
    {node: (count before, count after)}."""
    counts = {}
    for name, node in trainer.model.gaussian_nodes().items():
        before = node.num_gaussians
        if before == 0:
            counts[name] = (0, 0)
            continue
        keep = keep_top(contributions[name], fraction, node.gaussian_buffers.get("instance"))
        trainer.optimizers.replace_gaussian_rows(name, node, lambda k, t: t[keep], lambda k, s: s[keep])
        order = node.row_order()  # a boolean selection keeps row order; a node may still want its own
        if order is not None:
            trainer.optimizers.replace_gaussian_rows(name, node, lambda k, t: t[order], lambda k, s: s[order])
        trainer.strategy.state.pop(name, None)  # densification statistics of the old rows
        counts[name] = (before, node.num_gaussians)
    return counts
