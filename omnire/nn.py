"""Small neural building blocks shared by node types (deformation fields)."""
from __future__ import annotations

import math

import torch
from torch import nn


def positional_encoding(x: torch.Tensor, num_freqs: int) -> torch.Tensor:
    """(..., D) -> (..., 2 * num_freqs * D): sin and cos of 2^k pi x for k < num_freqs."""
    freqs = (2.0 ** torch.arange(num_freqs, device=x.device, dtype=x.dtype)) * math.pi  # (L,)
    angles = (x[..., None, :] * freqs[:, None]).flatten(-2)  # (..., L*D)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


class DeformationMLP(nn.Module):
    """ReLU MLP with one skip connection: (N, in_dim) -> (d_mu (N,3), d_q (N,4), d_s (N,3)).

    ``depth`` hidden layers of ``width``; the input is concatenated to the input of hidden
    layer ``skip`` (DeformableGS / OmniRe: depth 8, width 256, skip 4). The output layer
    starts at zero so a field begins as the identity (no jump when a warm-up ends).
    """

    def __init__(self, in_dim: int, depth: int, width: int, skip: int) -> None:
        super().__init__()
        self.skip = skip
        layers = []
        for i in range(depth):
            d_in = in_dim if i == 0 else width
            if i == skip and i > 0:
                d_in += in_dim
            layers.append(nn.Linear(d_in, width))
        self.layers = nn.ModuleList(layers)
        self.out = nn.Linear(width, 10)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        h = x
        for i, layer in enumerate(self.layers):
            if i == self.skip and i > 0:
                h = torch.cat([h, x], dim=-1)
            h = torch.relu(layer(h))
        o = self.out(h)
        return o[:, :3], o[:, 3:7], o[:, 7:10]
