"""The rasterizer interface every backend implements (reference PyTorch, native CPU, gsplat).

A rasterizer turns activated 3D Gaussians plus one pinhole camera into an image. Backends
register a :class:`~omnire.registry.RasterizerSpec`; :func:`select_backend` picks one.

Every backend implements :class:`Rasterizer` (``rasterize``, contract below). A backend may
also offer the optional paths of :data:`CAPABILITIES`, each a protocol of its own, and
declares the ones it offers in its spec's ``capabilities``: the runtime takes a path only
when it is declared, and a backend declaring a path it lacks is refused (at registration when
its factory is the class, else when it is built). The first three give the same pixels as
``rasterize`` up to float rounding; they only save time and memory. The fourth is a sensor:

- ``inference`` (:class:`InferenceRasterizer`): renders raw Gaussians in parts under
  ``torch.no_grad()`` (activation, SH colour and view culling in the backend).
- ``fused_training`` (:class:`FusedTrainingRasterizer`): the same with gradients, for
  the training step.
- ``ssim`` (:class:`SsimRasterizer`): a native SSIM map for the D-SSIM loss.
- ``lidar`` (:class:`LidarRasterizer`): renders a spinning LiDAR's rays (contract below).

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

Contract of :meth:`LidarRasterizer.rasterize_lidar(splats, rays, settings)` (N Gaussians,
F feature channels, R rays):

Inputs
    splats (:class:`Splats`) as above, except that ``colors`` (N, F) holds the per-Gaussian
        LiDAR features (intensity, ray-drop logit, ...: the caller chooses F >= 1).
    rays (:class:`LidarRays`):
        sensor_to_world (4, 4) the sensor pose; sensor axes x forward, y left, z up
                   (docs/lidar.md).
        azimuth_deg (R,) counter-clockwise from +x, any real value (taken modulo 360).
        elevation_deg (R,) above the sensor's x-y plane, in (-90, 90).
        min_range, max_range: metres; 0 <= min_range < max_range.
        probe_range (R,) or None: metres along each ray at which to report the
                   transmittance (e.g. just past a recorded return; finite).
        The rays need not lie on a grid (a :class:`~omnire.data.scene.BeamModel`'s grid and
        the directions of recorded returns both work).
    settings (:class:`LidarSettings`):
        eps_deg2: low-pass term added to the angular covariance diagonal (degrees^2), the
                   analogue of eps2d.

Outputs (:class:`LidarRenderOutput`)
    range        (R,) expected range sum_i w_i r_i / max(alpha, 1e-10) (0 where alpha = 0).
    median_range (R,) r_k of the first Gaussian k whose weight brings the ray's transmittance
                 from above 0.5 to 0.5 or below; ``max_range`` where it never falls to 0.5
                 (alpha < 0.5: no surface within the sensor's range).
    features     (R, F) = sum_i w_i f_i (no background).
    alpha        (R,) = sum_i w_i.
    probe_transmittance (R,) or None (when ``probe_range`` is None): prod (1 - alpha_i) over
                 the ray's composited Gaussians with r_i < probe_range (1 where none): the
                 light left at the probe. Its gradient reaches the alphas (opacities and
                 angular terms), not r_i (a step in r_i, as the median range's in alpha).

Geometry (omnire/lidarprojection.py): each Gaussian is mapped to the sensor's sphere: its
mean to (azimuth, elevation) and its covariance to a 2D angular one through the Jacobian of
the spherical map at the mean (degrees), plus ``eps_deg2``; a ray meets it with
alpha_i = min(0.99, o_i exp(-0.5 d^T Sigma_ang^-1 d)), d = (azimuth offset wrapped to
[-180, 180), elevation offset). Its range on the ray is the distance of maximum 3D response
along the ray, r_i = d^T S^-1 (mu - o) / d^T S^-1 d (S the covariance, o the sensor
origin, d the unit ray direction): on a flat Gaussian this is where the ray crosses it,
which the centre distance misses by decimetres at grazing angles (docs/lidar.md,
"Rendering LiDAR"). Gaussians are composited in the order of their centres' distance, with
the thresholds of the camera path (alpha >= 1/255, at most 0.99, stop before the
transmittance drops below 1e-4). Gaussians whose centre is not strictly between
``min_range`` and ``max_range``, or lies within 1 degree of the sensor's vertical axis (where
the spherical map is singular; no spinning LiDAR looks there), are not drawn; a pair whose
r_i is undefined (omnire/lidarprojection.py) or outside [min_range, max_range] is skipped.
Gradients flow to the splats; the rays and the sensor pose receive none. Bad input raises
:class:`RasterInputError`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Optional, Protocol

import torch

from omnire.camera import Camera
from omnire.errors import ConfigError

if TYPE_CHECKING:
    from omnire.data.scene import BeamModel
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


@dataclasses.dataclass(frozen=True)
class LidarRays:
    """The rays of one LiDAR render (see the module docstring for shapes and conventions)."""

    sensor_to_world: torch.Tensor
    azimuth_deg: torch.Tensor
    elevation_deg: torch.Tensor
    min_range: float
    max_range: float
    probe_range: Optional[torch.Tensor] = None

    def __len__(self) -> int:
        return self.azimuth_deg.shape[0]

    @classmethod
    def from_beam_model(cls, sensor_to_world: torch.Tensor, model: "BeamModel") -> "LidarRays":
        """Every ray of one revolution of ``model`` (beam-major, as ``BeamModel.directions``)
        from the pose ``sensor_to_world`` (4, 4), with the model's range limits."""
        B, A = model.num_beams, model.num_azimuths
        dtype = sensor_to_world.dtype
        az = (torch.arange(A, dtype=torch.float64) * (360.0 / A)).repeat(B)
        el = torch.as_tensor(model.elevations_deg, dtype=torch.float64).repeat_interleave(A)
        return cls(sensor_to_world, az.to(dtype), el.to(dtype), float(model.min_range), float(model.max_range))


@dataclasses.dataclass(frozen=True)
class LidarSettings:
    """Per-call LiDAR rendering settings (see the module docstring)."""

    eps_deg2: float = 0.01
    """Low-pass term added to the angular covariance diagonal, degrees^2: 0.3 (the camera's
    eps2d in pixels^2) times a 0.2-degree ray spacing squared, rounded."""


@dataclasses.dataclass
class LidarRenderOutput:
    """Per ray (R rays, F feature channels): range (R,), median_range (R,), features (R, F),
    alpha (R,), probe_transmittance (R,) or None (see the module docstring)."""

    range: torch.Tensor
    median_range: torch.Tensor
    features: torch.Tensor
    alpha: torch.Tensor
    probe_transmittance: Optional[torch.Tensor] = None


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


class LidarRasterizer(Protocol):
    """The ``lidar`` capability: a LiDAR's rays rendered from the splats, with gradients to
    them (contract in the module docstring)."""

    def rasterize_lidar(self, splats: Splats, rays: LidarRays, settings: LidarSettings = LidarSettings()
                        ) -> LidarRenderOutput:
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
    "lidar": Capability("rasterize_lidar", LidarRasterizer, "LiDAR sweeps cannot be rendered through this backend"),
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


def _check_shapes(expect: dict[str, tuple[torch.Tensor, tuple[int, ...]]]) -> None:
    """Each named tensor has its shape and a floating dtype."""
    for name, (t, shape) in expect.items():
        if tuple(t.shape) != shape:
            raise RasterInputError(f"{name}: shape {tuple(t.shape)}, expected {shape}")
        if not t.is_floating_point():
            raise RasterInputError(f"{name}: dtype {t.dtype}, expected a floating type")


def _check_finite(named: list[tuple[str, torch.Tensor]], what: str) -> None:
    """Each named tensor is finite (the error counts the bad values and lists the first rows)."""
    for name, t in named:
        bad = ~torch.isfinite(t.detach())
        if bool(bad.any()):
            rows = bad.reshape(t.shape[0], -1).any(dim=1).nonzero().flatten()[:5].tolist() if t.ndim else []
            raise RasterInputError(f"{name}: {int(bad.sum())} non-finite values (first rows {rows}); "
                                   f"refusing to render {what}")


def _splat_shapes(splats: Splats) -> tuple[int, dict[str, tuple[torch.Tensor, tuple[int, ...]]]]:
    """Gaussian count N and the expected shapes of the splats' tensors but ``colors``."""
    N = splats.means.shape[0] if splats.means.ndim == 2 else -1
    return N, {"means": (splats.means, (N, 3)), "quats": (splats.quats, (N, 4)), "scales": (splats.scales, (N, 3)),
               "opacities": (splats.opacities, (N,))}


def _splat_tensors(splats: Splats) -> list[tuple[str, torch.Tensor]]:
    return [("means", splats.means), ("scales", splats.scales), ("quats", splats.quats),
            ("opacities", splats.opacities), ("colors", splats.colors)]


def _check_scales(splats: Splats) -> None:
    if bool((splats.scales.detach() < 0).any()):
        raise RasterInputError("scales: negative values; pass activated (exp'ed) scales")


def check_raster_inputs(splats: Splats, camera: Camera, settings: RasterSettings) -> None:
    """Boundary check shared by all backends: shapes, dtypes, finiteness."""
    colors = splats.colors
    viewmat, K = camera.world_to_cam, camera.K
    N, expect = _splat_shapes(splats)
    _check_shapes({**expect, "viewmat": (viewmat, (4, 4)), "K": (K, (3, 3))})
    if colors.ndim != 2 or colors.shape[0] != N:
        raise RasterInputError(f"colors: shape {tuple(colors.shape)}, expected ({N}, D)")
    background = settings.background
    if background is not None and tuple(background.shape) != (colors.shape[1],):
        raise RasterInputError(f"background: shape {tuple(background.shape)}, expected ({colors.shape[1]},)")
    _check_finite(_splat_tensors(splats) + [("viewmat", viewmat), ("K", K)], "a NaN image")
    _check_scales(splats)


def check_lidar_inputs(splats: Splats, rays: LidarRays, settings: LidarSettings) -> None:
    """Boundary check of :meth:`LidarRasterizer.rasterize_lidar` shared by all backends:
    shapes, dtypes, finiteness, elevations in (-90, 90), the range limits and eps_deg2."""
    colors = splats.colors
    N, expect = _splat_shapes(splats)
    R = rays.azimuth_deg.shape[0] if rays.azimuth_deg.ndim == 1 else -1
    _check_shapes({**expect, "sensor_to_world": (rays.sensor_to_world, (4, 4)), "azimuth_deg": (rays.azimuth_deg, (R,)),
                   "elevation_deg": (rays.elevation_deg, (R,))})
    if colors.ndim != 2 or colors.shape[0] != N or colors.shape[1] < 1:
        raise RasterInputError(f"colors: shape {tuple(colors.shape)}, expected ({N}, F) with F >= 1 LiDAR features")
    probe = [] if rays.probe_range is None else [("probe_range", rays.probe_range)]
    if probe and tuple(rays.probe_range.shape) != (R,):
        raise RasterInputError(f"probe_range: shape {tuple(rays.probe_range.shape)}, expected ({R},) like azimuth_deg")
    _check_finite(_splat_tensors(splats) + [("sensor_to_world", rays.sensor_to_world),
                                            ("azimuth_deg", rays.azimuth_deg), ("elevation_deg", rays.elevation_deg)]
                  + probe, "a NaN sweep")
    _check_scales(splats)
    if bool((rays.elevation_deg.detach().abs() >= 90.0).any()):
        raise RasterInputError("elevation_deg: values outside (-90, 90) degrees")
    lo, hi = rays.min_range, rays.max_range
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi):
        raise RasterInputError(f"min_range, max_range: {lo}, {hi}; expected finite metres with "
                               "0 <= min_range < max_range")
    if not (math.isfinite(settings.eps_deg2) and settings.eps_deg2 >= 0.0):
        raise RasterInputError(f"eps_deg2: {settings.eps_deg2}, expected a finite value >= 0 (degrees^2)")


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
