"""The rasterizer interface every backend implements (reference PyTorch, native CPU, gsplat).

A rasterizer turns activated 3D Gaussians plus one pinhole camera into an image. Backends
register a :class:`~omnire.registry.RasterizerSpec`; :func:`select_rasterizer` picks one.

Contract of :meth:`Rasterizer.rasterize(splats, camera, settings)` (N Gaussians, D colour
channels, image H x W):

Inputs
    splats (:class:`Splats`), activated Gaussians:
        means      (N, 3) world positions.
        quats      (N, 4) rotations wxyz, *not necessarily normalised* (zero quats allowed:
                   treated as identity).
        scales     (N, 3) positive standard deviations (already exp'ed).
        opacities  (N,)   in [0, 1] (already sigmoid'ed).
        colors     (N, D) per-Gaussian colour (view-dependent SH is evaluated by the caller).
    camera (:class:`omnire.camera.Camera`): K (3, 3) in pixels with pixel centres at +0.5,
        the view matrix ``camera.world_to_cam`` (OpenCV axes), ``width`` x ``height``.
    settings (:class:`RasterSettings`):
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

Gradients flow to the splats and the background; the camera receives none (camera poses
are not optimised through the rasterizer).

Per-pixel compositing: Gaussians sorted by camera depth, alpha_i = min(0.99, o_i *
exp(-0.5 d^T Sigma2d^-1 d)), skipped when alpha_i < 1/255, and a pixel stops once its
transmittance would drop below 1e-4. Non-finite inputs raise :class:`RasterInputError`.
"""
from __future__ import annotations

import dataclasses
from typing import Optional, Protocol

import torch

from omnire.camera import Camera
from omnire.errors import ConfigError

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


@dataclasses.dataclass
class Splats:
    """Activated Gaussians ready to rasterize (see the module docstring for shapes)."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor

    def __len__(self) -> int:
        return self.means.shape[0]


@dataclasses.dataclass(frozen=True)
class RasterSettings:
    """Per-call rasterizer settings (see the module docstring)."""

    background: Optional[torch.Tensor] = None
    near: float = 0.01
    far: float = 1e10
    eps2d: float = 0.3


class Rasterizer(Protocol):
    """What every backend provides. ``name`` is its registry name."""

    name: str

    def rasterize(self, splats: Splats, camera: Camera, settings: RasterSettings = RasterSettings()) -> RenderOutput:
        ...


def check_raster_inputs(splats: Splats, camera: Camera, settings: RasterSettings) -> None:
    """Boundary check shared by all backends: shapes, dtypes, finiteness."""
    means, quats, scales, opacities, colors = (splats.means, splats.quats, splats.scales, splats.opacities,
                                               splats.colors)
    viewmat, K = camera.world_to_cam, camera.K
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
    background = settings.background
    if background is not None and tuple(background.shape) != (colors.shape[1],):
        raise RasterInputError(f"background: shape {tuple(background.shape)}, expected ({colors.shape[1]},)")
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


def select_rasterizer(plugins, name: str = "auto", device: torch.device | str = "cpu", **kwargs) -> Rasterizer:
    """Build the rasterizer ``name``, or with ``auto`` the available one of highest priority.

    An ``available()`` that raises is reported as a failure of its plugin and that backend is
    skipped (unless it is the one asked for by name). Raises :class:`ConfigError` naming every
    candidate and why it is unavailable when none is.
    """
    device = torch.device(device)
    registry = plugins.rasterizers
    if name != "auto":
        spec = registry.get(name)
        ok, reason = spec.available(device)
        if not ok:
            raise ConfigError(f"--method.rasterizer {name}: not available on {device}: {reason}")
        return spec.factory(**kwargs)
    reasons = []
    for spec in sorted(registry, key=lambda s: -s.priority):
        probe = plugins.call(registry, spec.name, "rasterizer available()", lambda spec=spec: spec.available(device))
        if probe is None:
            reasons.append(f"{spec.name}: its available() failed")
            continue
        ok, reason = probe
        if ok:
            return spec.factory(**kwargs)
        reasons.append(f"{spec.name}: {reason}")
    raise ConfigError(f"no rasterizer available on {device}: " + "; ".join(reasons) if reasons else
                      "no rasterizer registered (install omnire-rasterizer-torch)")
