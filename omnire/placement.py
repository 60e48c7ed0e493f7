"""Box-local Gaussians placed in the world by per-instance poses.

An actor node's Gaussians live in their boxes; a frame places each present instance's
rows by its box pose. :class:`Placement` holds those poses, one per segment of rows (an
instance); :meth:`Placement.apply` gives the world Gaussians (one matrix product per
instance). A rasterizer that draws rows under a per-segment move (the cpu rasterizer's
training path, ``rasterize_gaussians_train(..., placements=...)``) takes the box-local rows
and the poses instead, so no world copy is made (:class:`omnire.nodes.base.NodeOutput`
computes one only when something reads it); with ``Placement.starts`` it reads a node's
parameters in place, so not even the present instances' rows are gathered.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import torch

from omnire.gaussians import GAUSSIAN_KEYS, Gaussians
from omnire.geometry import quat_left_matrix, rotmat_to_quat
from omnire.rowsparse import gather_rows


@dataclasses.dataclass(frozen=True)
class Placement:
    """Rows in segments, segment p (``lengths[p]`` rows) placed by x -> R[p] x + t[p],
    quaternions q -> quat(R[p]) q.

    Attributes:
        lengths: (P) python ints, the rows of each segment (zero allowed).
        R: (P, 3, 3) rotations; t: (P, 3) translations (gradients reach both).
        starts: (P) python ints, where each segment's rows start in the Gaussians placed,
            increasing and not overlapping: those Gaussians are then a node's own parameters
            (other rows too, which are not drawn and get no gradient), so nothing is copied
            (:meth:`apply` gathers the rows with row-sparse gradients). None: the segments
            are the Gaussians' rows in order.
    """

    lengths: list[int]
    R: torch.Tensor
    t: torch.Tensor
    starts: Optional[list[int]] = None

    def __post_init__(self) -> None:
        P = len(self.lengths)
        if self.R.shape != (P, 3, 3) or self.t.shape != (P, 3) or any(n < 0 for n in self.lengths):
            raise ValueError(f"Placement: {P} segment lengths need R ({P}, 3, 3) and t ({P}, 3), got "
                             f"{tuple(self.R.shape)} and {tuple(self.t.shape)}")
        if self.starts is not None:
            if len(self.starts) != P:
                raise ValueError(f"Placement: {len(self.starts)} starts for {P} segments")
            ends = [s + n for s, n in zip(self.starts, self.lengths)]
            if any(s < 0 for s in self.starts) or any(b < a for a, b in zip(ends, self.starts[1:])):
                raise ValueError("Placement: segment starts must be non-negative, increasing and not overlapping")

    @property
    def num_rows(self) -> int:
        """Rows drawn (the segments' total)."""
        return sum(self.lengths)

    @functools.cached_property
    def rows(self) -> Optional[torch.Tensor]:
        """(num_rows,) increasing rows of the segments in the Gaussians placed (``starts``
        given), else None."""
        if self.starts is None:
            return None
        device = self.R.device
        lengths = torch.tensor(self.lengths, dtype=torch.long, device=device)
        starts = torch.tensor(self.starts, dtype=torch.long, device=device)
        # row k = its segment's start + (k - the first output index of its segment)
        shift = torch.repeat_interleave(starts - (torch.cumsum(lengths, 0) - lengths), lengths, output_size=self.num_rows)
        return shift + torch.arange(self.num_rows, device=device)

    def check_source(self, num_gaussians: int) -> None:
        """Raise ValueError unless Gaussians of ``num_gaussians`` rows can be placed."""
        if self.starts is None:
            if num_gaussians != self.num_rows:
                raise ValueError(f"Placement: {num_gaussians} Gaussians, the segments hold {self.num_rows} rows")
        elif self.starts and self.starts[-1] + self.lengths[-1] > num_gaussians:
            raise ValueError(f"Placement: segments reach row {self.starts[-1] + self.lengths[-1]} of "
                             f"{num_gaussians} Gaussians")

    def apply(self, g: Gaussians) -> Gaussians:
        """World Gaussians (num_rows) of the segments' rows of box-local ``g``."""
        self.check_source(len(g))
        if self.rows is not None:
            g = Gaussians(*(gather_rows(getattr(g, k), self.rows) for k in GAUSSIAN_KEYS))
        L = quat_left_matrix(rotmat_to_quat(self.R))  # (P, 4, 4): quat_multiply(q, b) == L @ b
        means, quats = _SegmentTransform.apply(g.means.contiguous(), g.quats.contiguous(), self.R, self.t, L,
                                               self.lengths)
        return dataclasses.replace(g, means=means, quats=quats)


class _SegmentTransform(torch.autograd.Function):
    """Rigid transforms of contiguous row segments: the ``lengths[p]`` rows of segment p get
    means (n,3) -> means @ R[p].T + t[p] and quats (n,4) -> quats @ L[p].T (L: the
    quaternion's left-multiplication matrix), one matrix product per segment. Inputs: means
    (M,3), quats (M,4), R (P,3,3), t (P,3), L (P,4,4), lengths (P python ints, sum M).
    Backward: row gradients g @ R[p] and g @ L[p]; pose gradients per segment, dR = g^T means,
    dt = sum of g, dL = g_q^T quats (tested against :func:`transform_rows` with gradcheck)."""

    @staticmethod
    def forward(ctx, means, quats, R, t, L, lengths):
        out_m, out_q = torch.empty_like(means), torch.empty_like(quats)
        # contiguous transposes: a transposed 3x3 operand takes a slower matrix-product path
        # (4x on a loaded machine), and addmm's bias broadcast is slower than a separate add
        RT, LT = R.transpose(1, 2).contiguous(), L.transpose(1, 2).contiguous()
        a = 0
        for p, n in enumerate(lengths):
            if n:
                torch.mm(means[a:a + n], RT[p], out=out_m[a:a + n]).add_(t[p])
                torch.mm(quats[a:a + n], LT[p], out=out_q[a:a + n])
            a += n
        ctx.save_for_backward(means, quats, R, L)
        ctx.lengths = lengths
        return out_m, out_q

    @staticmethod
    def backward(ctx, g_m, g_q):
        means, quats, R, L = ctx.saved_tensors
        need = ctx.needs_input_grad
        g_m, g_q = g_m.contiguous(), g_q.contiguous()
        g_means = torch.empty_like(means) if need[0] else None
        g_quats = torch.empty_like(quats) if need[1] else None
        g_R = torch.zeros_like(R) if need[2] else None
        g_t = torch.zeros(R.shape[0], 3, dtype=R.dtype, device=R.device) if need[3] else None
        g_L = torch.zeros_like(L) if need[4] else None
        a = 0
        for p, n in enumerate(ctx.lengths):
            if n:
                gm, gq = g_m[a:a + n], g_q[a:a + n]
                if g_means is not None:
                    torch.mm(gm, R[p], out=g_means[a:a + n])
                if g_quats is not None:
                    torch.mm(gq, L[p], out=g_quats[a:a + n])
                if g_R is not None:
                    g_R[p] = gm.T @ means[a:a + n]
                if g_t is not None:
                    g_t[p] = gm.sum(0)
                if g_L is not None:
                    g_L[p] = gq.T @ quats[a:a + n]
            a += n
        return g_means, g_quats, g_R, g_t, g_L, None
