"""The rasterizer interface every backend implements (reference PyTorch, native CPU, gsplat).

A rasterizer turns activated 3D Gaussians plus one pinhole camera into an image. Backends
register a :class:`~omnire.registry.RasterizerSpec`; :func:`select_backend` picks one.

Every backend implements :class:`Rasterizer` (``rasterize``, contract below). A backend may
also offer the optional paths of :data:`CAPABILITIES`, each a protocol of its own, and
declares the ones it offers in its spec's ``capabilities``: the runtime takes a path only
when it is declared, and a backend declaring a path it lacks is refused (at registration when
its factory is the class, else when it is built). The paths give the same pixels as
``rasterize`` up to float rounding; they only save time and memory:

- ``inference`` (:class:`InferenceRasterizer`): renders raw Gaussians in parts under
  ``torch.no_grad()`` (activation, SH colour and view culling in the backend).
- ``fused_training`` (:class:`FusedTrainingRasterizer`): the same with gradients, for
  the training step.
- ``ssim`` (:class:`SsimRasterizer`): a native SSIM map for the D-SSIM loss.

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
from typing import TYPE_CHECKING, Optional, Protocol

import torch

from omnire.camera import Camera
from omnire.errors import ConfigError

if TYPE_CHECKING:
    from omnire.gaussians import Gaussians
    from omnire.placement import Placement

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_ALPHA = 0.99
TRANSMITTANCE_MIN = 1e-4
TILE_SIZE = 16


class RasterInputError(ValueError):
    """Invalid rasterizer input; the message names the tensor and what was expected."""


@dataclasses.dataclass
class RenderOutput:
    """What a rasterizer returns (see the module docstring); ``timings``: wall seconds of
    the stages the backend measured, by name (empty when it measures none; profiles only)."""

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    radii: torch.Tensor
    means2d: torch.Tensor
    absgrad2d: torch.Tensor
    timings: dict[str, float] = dataclasses.field(default_factory=dict)


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


class InferenceRasterizer(Protocol):
    """The ``inference`` capability: raw Gaussians (unactivated, SH coefficients) of several
    node outputs rendered without gradients; ``moved`` and ``placements`` as
    :class:`FusedTrainingRasterizer` takes them. Returns the image and how many rows it drew."""

    def rasterize_gaussians(self, parts: list["Gaussians"], camera: Camera, sh_degree: int,
                            settings: RasterSettings = RasterSettings(), cull: bool = True,
                            moved: Optional[tuple[torch.Tensor, torch.Tensor]] = None,
                            placements: Optional[list[Optional["Placement"]]] = None
                            ) -> tuple[RenderOutput, int]:
        ...


class FusedTrainingRasterizer(Protocol):
    """The ``fused_training`` capability: :class:`InferenceRasterizer`'s path with gradients
    to the parts' raw parameters; ``moved`` (rotation (3, 3), translation (3,)) moves every
    Gaussian first (a camera-pose correction), ``placements`` (one per part, or None) draws a
    part's box-local rows under its poses."""

    def rasterize_gaussians_train(self, parts: list["Gaussians"], camera: Camera, sh_degree: int,
                                  settings: RasterSettings = RasterSettings(), cull: bool = True,
                                  moved: Optional[tuple[torch.Tensor, torch.Tensor]] = None,
                                  placements: Optional[list[Optional["Placement"]]] = None
                                  ) -> tuple[RenderOutput, int]:
        ...


class SsimRasterizer(Protocol):
    """The ``ssim`` capability: (H, W, C) x2 -> (H, W, 1) SSIM map with the contract and
    numbers of :func:`omnire.losses.ssim_map`."""

    def ssim_map(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        ...


@dataclasses.dataclass(frozen=True)
class Capability:
    """An optional rasterizer path: the method that provides it and what a run without it does."""

    method: str
    protocol: type
    without: str


CAPABILITIES: dict[str, Capability] = {
    "inference": Capability("rasterize_gaussians", InferenceRasterizer,
                            "renders without gradients concatenate the node outputs and call rasterize"),
    "fused_training": Capability("rasterize_gaussians_train", FusedTrainingRasterizer,
                                 "training steps concatenate the node outputs and call rasterize (autograd)"),
    "ssim": Capability("ssim_map", SsimRasterizer, "the D-SSIM loss uses omnire.losses.ssim_map (PyTorch)"),
}
"""The optional rasterizer paths by capability name (see the module docstring)."""


def lacking(backend, capabilities) -> list[str]:
    """The capabilities among ``capabilities`` that ``backend`` (a class or an instance)
    has no method for."""
    return [c for c in sorted(capabilities) if not callable(getattr(backend, CAPABILITIES[c].method, None))]


def describe_paths(capabilities: frozenset[str]) -> str:
    """One line: which path each optional capability takes (for ``omnire plugins`` and the
    run log)."""
    return "; ".join(f"{name}: {'native ' + c.method if name in capabilities else 'missing, so ' + c.without}"
                     for name, c in CAPABILITIES.items())


def summarize_paths(capabilities: frozenset[str]) -> str:
    """Short form of :func:`describe_paths` (a table cell)."""
    missing = [c for c in CAPABILITIES if c not in capabilities]
    have = [c for c in CAPABILITIES if c in capabilities]
    return (f"rasterize + {', '.join(have)}" if have else "rasterize only") + (
        f"; missing: {', '.join(missing)}" if missing else "")


@dataclasses.dataclass(frozen=True)
class RasterBackend:
    """A built rasterizer and the optional paths its spec declares (checked present)."""

    rasterizer: Rasterizer
    capabilities: frozenset[str]

    @property
    def name(self) -> str:
        return self.rasterizer.name

    def describe(self) -> str:
        """For the run log: the backend and which path each capability takes."""
        return f"rasterizer {self.name}: {describe_paths(self.capabilities)}"


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
    """The rasterizer of :func:`select_backend` (same arguments)."""
    return select_backend(plugins, name, device, **kwargs).rasterizer


def build_backend(spec, **kwargs) -> RasterBackend:
    """Build ``spec``'s rasterizer; a backend lacking a capability its spec declares is refused."""
    rasterizer = spec.factory(**kwargs)
    missing = lacking(rasterizer, spec.capabilities)
    if missing:
        raise ConfigError(f"rasterizer {spec.name!r} declares capabilities {missing} but its object has no "
                          + ", ".join(CAPABILITIES[c].method for c in missing) + "; fix its RasterizerSpec")
    return RasterBackend(rasterizer, frozenset(spec.capabilities))


def select_backend(plugins, name: str = "auto", device: torch.device | str = "cpu", **kwargs) -> RasterBackend:
    """Build the rasterizer ``name``, or with ``auto`` the available one of highest priority,
    with its declared capabilities.

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
        return build_backend(spec, **kwargs)
    reasons = []
    for spec in sorted(registry, key=lambda s: -s.priority):
        probe = plugins.call(registry, spec.name, "rasterizer available()", lambda spec=spec: spec.available(device))
        if probe is None:
            reasons.append(f"{spec.name}: its available() failed")
            continue
        ok, reason = probe
        if ok:
            return build_backend(spec, **kwargs)
        reasons.append(f"{spec.name}: {reason}")
    raise ConfigError(f"no rasterizer available on {device}: " + "; ".join(reasons) if reasons else
                      "no rasterizer registered (install omnire-rasterizer-torch)")
