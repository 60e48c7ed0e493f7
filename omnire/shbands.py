"""SH coefficients stored up to the degree training uses, not the nodes' final degree.

Training raises the SH degree every ``sh_degree_interval`` steps (0 -> 3). Bands above the
current degree get no gradient, so until they start they are zeros with zero Adam moments,
yet every step would still carry them through the rasterizer's gradient, Adam (a read and a
write of the parameter and both moments) and every gather of the actor nodes: band 3 alone
is 21 of a Gaussian's 59 numbers. :func:`fit_sh_bands` keeps each node's ``shN`` (N, K, 3)
at the columns of the current degree (at most the node's own ``sh_degree``): it drops
columns that are all zero with zero moments, and appends zero columns (zero moments) when
the degree rises. A band that starts from zero coefficients with zero moments is exactly
what dense Adam would hold for it, and the step counter belongs to the tensor, so training
takes the same steps as with all bands stored.
"""
from __future__ import annotations

from typing import Optional

import torch

from omnire.gaussians import num_sh_bases


def node_max_degree(node) -> int:
    """The SH degree a node is configured for (``config.sh_degree``; 3 when it has none)."""
    return int(getattr(getattr(node, "config", None), "sh_degree", 3))


def _moments(optimizers, name: str, param: torch.Tensor) -> list[torch.Tensor]:
    opt = optimizers.optimizers.get(name) if optimizers is not None else None
    state = opt.state.get(param, {}) if opt is not None else {}
    return [v for k, v in state.items() if k != "step" and torch.is_tensor(v) and v.shape == param.shape]


def fit_sh_bands(nodes: dict, optimizers, degree: int, discard_unused: bool = False) -> dict[str, tuple[int, int]]:
    """Resize every node's ``shN`` to the columns of SH ``degree`` (capped by the node's own
    degree), its Adam moments with it. Columns beyond them are dropped only when they and
    their moments are all zero, unless ``discard_unused`` (benchmarks that replay a step of
    an earlier degree from a later checkpoint). Returns {node: (columns before, after)} of
    the nodes changed."""
    changed: dict[str, tuple[int, int]] = {}
    for name, node in nodes.items():
        params = getattr(node, "gaussian_params", None)
        if params is None or "shN" not in params:
            continue
        shN = params["shN"]
        have = shN.shape[1]
        want = num_sh_bases(min(degree, node_max_degree(node))) - 1
        if have == want:
            continue
        if have > want and not discard_unused:
            extra = [shN.detach()[:, want:]] + [m[:, want:] for m in _moments(optimizers, name, shN)]
            if any(bool(t.any()) for t in extra):
                continue  # trained bands (e.g. a checkpoint of a later degree): kept

        def resize(key: str, t: torch.Tensor, want: int = want) -> torch.Tensor:
            if key != "shN":
                return t
            if t.shape[1] >= want:
                return t[:, :want].clone()
            return torch.cat([t, t.new_zeros(t.shape[0], want - t.shape[1], *t.shape[2:])], 1)

        if optimizers is not None:
            optimizers.replace_gaussian_rows(name, node, resize, resize)
        else:
            node.set_gaussian_tensors({"shN": resize("shN", shN.detach())})
        changed[name] = (have, want)
    return changed


def sh_columns(nodes: dict) -> dict[str, Optional[int]]:
    """{node: columns of its stored ``shN``} (None for nodes without one)."""
    out: dict[str, Optional[int]] = {}
    for name, node in nodes.items():
        params = getattr(node, "gaussian_params", None)
        out[name] = int(params["shN"].shape[1]) if params is not None and "shN" in params else None
    return out
