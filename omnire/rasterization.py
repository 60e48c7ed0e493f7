"""The rasterizer interface every backend implements (reference PyTorch, native CPU, gsplat).

A rasterizer turns activated 3D Gaussians plus one pinhole camera into an image. Backends
register a :class:`~omnire.registry.RasterizerSpec`; :func:`select_rasterizer` picks one.

Contract of :meth:`Rasterizer.rasterize` (N Gaussians, D colour channels, image H x W):

Inputs
    means      (N, 3) world positions.
    quats      (N, 4) rotations wxyz, *not necessarily normalised* (zero quats allowed:
               treated as identity).
    scales     (N, 3) positive standard deviations (already exp'ed).
    opacities  (N,)   in [0, 1] (already sigmoid'ed).
    colors     (N, D) per-Gaussian colour (view-dependent SH is evaluated by the caller).
    viewmat    (4, 4) world-to-camera, OpenCV axes.
    K          (3, 3) pinhole intrinsics in pixels, pixel centres at +0.5.
    width, height: image size.
    background (D,) colour composited under the splats, or None (black).
    near, far: depth clipping planes; Gaussians with camera z outside are culled.
    eps2d:     low-pass term added to the 2D covariance diagonal (pixels^2), as in 3DGS.

Outputs (:class:`RenderOutput`)
    rgb       (H, W, D) = sum_i w_i c_i + (1 - alpha) background, w_i = a_i T_i.
    depth     (H, W, 1) expected depth sum_i w_i z_i / max(alpha, 1e-10).
    alpha     (H, W, 1) = sum_i w_i.
    radii     (N,) int screen radius in pixels (0 = culled / not rendered).
    means2d   (N, 2) projected centres in pixels (unspecified where radii == 0).
    absgrad2d (N, 2) float buffer, zero on return; after ``backward()`` it holds the
              per-Gaussian sum over pixels of |dL/d means2d| (AbsGrad, used by the
              densification strategy), in pixel units. Repeated backward passes
              accumulate into it, as ``.grad`` does.

Gradients flow to means, quats, scales, opacities, colors and background; ``viewmat`` and
``K`` receive none (camera poses are not optimised through the rasterizer).

Per-pixel compositing: Gaussians sorted by camera depth, alpha_i = min(0.99, o_i *
exp(-0.5 d^T Sigma2d^-1 d)), skipped when alpha_i < 1/255, and a pixel stops once its
transmittance would drop below 1e-4. Non-finite inputs raise :class:`RasterInputError`.
"""
from __future__ import annotations

import dataclasses
from typing import Optional, Protocol

import torch

from omnire.registry import RasterizerSpec, Registry

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_ALPHA = 0.99
TRANSMITTANCE_MIN = 1e-4
TILE_SIZE = 16


class RasterInputError(ValueError):
    """Invalid rasterizer input; the message names the tensor and what was expected."""


@dataclasses.dataclass
class RenderOutput:
    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    radii: torch.Tensor
    means2d: torch.Tensor
    absgrad2d: torch.Tensor


class Rasterizer(Protocol):
    """What every backend provides. ``name`` is its registry name."""

    name: str

    def rasterize(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        viewmat: torch.Tensor,
        K: torch.Tensor,
        width: int,
        height: int,
        background: Optional[torch.Tensor] = None,
        near: float = 0.01,
        far: float = 1e10,
        eps2d: float = 0.3,
    ) -> RenderOutput: ...


def check_raster_inputs(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: Optional[torch.Tensor] = None,
) -> None:
    """Boundary check shared by all backends: shapes, dtypes, finiteness."""
    N = means.shape[0] if means.ndim == 2 else -1
    expect = {
        "means": (means, (N, 3)),
        "quats": (quats, (N, 4)),
        "scales": (scales, (N, 3)),
        "opacities": (opacities, (N,)),
        "viewmat": (viewmat, (4, 4)),
        "K": (K, (3, 3)),
    }
    for name, (t, shape) in expect.items():
        if tuple(t.shape) != shape:
            raise RasterInputError(f"{name}: shape {tuple(t.shape)}, expected {shape}")
        if not t.is_floating_point():
            raise RasterInputError(f"{name}: dtype {t.dtype}, expected a floating type")
    if colors.ndim != 2 or colors.shape[0] != N:
        raise RasterInputError(f"colors: shape {tuple(colors.shape)}, expected ({N}, D)")
    if background is not None and tuple(background.shape) != (colors.shape[1],):
        raise RasterInputError(f"background: shape {tuple(background.shape)}, expected ({colors.shape[1]},)")
    if width <= 0 or height <= 0:
        raise RasterInputError(f"image size {width}x{height}: both must be positive")
    for name, t in [("means", means), ("scales", scales), ("quats", quats), ("opacities", opacities),
                    ("colors", colors), ("viewmat", viewmat), ("K", K)]:
        bad = ~torch.isfinite(t.detach())
        if bool(bad.any()):
            rows = bad.reshape(t.shape[0], -1).any(dim=1).nonzero().flatten()[:5].tolist() if t.ndim else []
            raise RasterInputError(
                f"{name}: {int(bad.sum())} non-finite values (first rows {rows}); "
                "refusing to render a NaN image"
            )
    if bool((scales.detach() < 0).any()):
        raise RasterInputError("scales: negative values; pass activated (exp'ed) scales")


def select_rasterizer(
    registry: Registry[RasterizerSpec], name: str = "auto", device: torch.device | str = "cpu", **kwargs
) -> Rasterizer:
    """Build the rasterizer ``name``, or with ``auto`` the available one of highest priority.

    Raises ValueError naming every candidate and why it is unavailable when none is.
    """
    device = torch.device(device)
    if name != "auto":
        spec = registry.get(name)
        ok, reason = spec.available(device)
        if not ok:
            raise ValueError(f"rasterizer {name!r} is not available on {device}: {reason}")
        return spec.factory(**kwargs)
    reasons = []
    for spec in sorted(registry, key=lambda s: -s.priority):
        ok, reason = spec.available(device)
        if ok:
            return spec.factory(**kwargs)
        reasons.append(f"{spec.name}: {reason}")
    raise ValueError(f"no rasterizer available on {device}: " + "; ".join(reasons) if reasons else
                     "no rasterizer registered (install omnire-rasterizer-torch)")
