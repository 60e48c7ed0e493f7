"""Pruning a trainer's scene graph to the Gaussians that contribute most, node by node."""
from __future__ import annotations

import torch

from omnire_compact.contribution import keep_top


@torch.no_grad()
def prune_nodes(trainer, contributions: dict[str, torch.Tensor], fraction: float) -> dict[str, tuple[int, int]]:
    """Keep, in every Gaussian node of ``trainer`` (an :class:`omnire.api.Trainer`), the
    ``fraction`` of its Gaussians with the largest ``contributions`` (per node, (N_node,)
    from :func:`~omnire_compact.contribution.node_contributions`); actor nodes keep that
    fraction of each instance (their ``instance`` buffer). Rows are cut by
    :meth:`omnire.api.Trainer.keep_gaussian_rows`, so training can continue from the result.
    Returns {node: (count before, count after)}."""
    counts = {}
    for name, node in trainer.recon.gaussian_nodes().items():
        if node.num_gaussians == 0:
            counts[name] = (0, 0)
            continue
        keep = keep_top(contributions[name], fraction, node.gaussian_buffers.get("instance"))
        counts[name] = trainer.keep_gaussian_rows(name, keep)
    return counts
