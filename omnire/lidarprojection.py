"""Spherical projection of 3D Gaussians for LiDAR rendering: the geometry of the ``lidar``
contract of :mod:`omnire.rasterization`, in PyTorch (differentiable), and the tiles of the
sphere that bin rays and Gaussians. Backends composite these per-Gaussian quantities (the
cpu one computes the same numbers natively, plugins/cpu-rasterizer/omnire_rasterizer_cpu/csrc/lidar.cpp).

Sensor frame x forward, y left, z up; azimuth counter-clockwise from +x in degrees,
elevation above the x-y plane in degrees (:func:`omnire.beams.spherical`). Shapes: N
Gaussians, R rays.

A Gaussian with mean m (sensor frame), covariance S and opacity o becomes

- its direction (azimuth, elevation) of m, in degrees;
- an angular covariance J S J^T + eps_deg2 I (degrees^2), J (2, 3) the Jacobian of
  (azimuth, elevation) at m in degrees per metre (the EWA linearisation of the camera path,
  with the spherical map in place of the pinhole's), stored as its inverse (the conic);
- the quadric that gives its range on a ray: the response along the ray x = t d is largest
  at t* = d^T S^-1 m / d^T S^-1 d (:func:`max_response_range`); S^-1 is stored scaled by the
  smallest variance (entries in [0, 1], same t*) as ``quad`` (6: xx, xy, xz, yy, yz, zz) and
  ``lin`` = quad m;
- its centre distance |m| (the compositing order) and the angular half-extents (azimuth,
  elevation) of the ellipse outside which its alpha is below 1/255 for sure (the binning).

A Gaussian is not drawn (``visible`` False) when its centre distance is not strictly
inside (min_range, max_range), its centre lies within :data:`POLE_MARGIN_DEG` of the
sensor's vertical axis (the azimuth is undefined there), its opacity is below 1/255, or its
angular covariance is degenerate.
"""
from __future__ import annotations

import dataclasses
import math

import torch

from omnire.geometry import lowpass_conics, quat_to_rotmat
from omnire.rasterization import ALPHA_THRESHOLD, LidarRays, Splats

POLE_MARGIN_DEG = 1.0
"""Gaussians whose centre is nearer than this to the sensor's vertical axis are not drawn."""

MIN_SCALE = 1e-12
"""Scales are clamped to this (metres) in the range quadric only, so that a zero scale gives
a finite S^-1."""

EXTENT_MARGIN = (1.01, 1e-3)
"""The binning extents are widened by 1% and 0.001 degrees so that rounding never drops a
pair the alpha test keeps (the alpha test decides; the extents only choose candidates)."""

MIN_RANGE_DENOMINATOR = 1e-12
"""A pair whose d^T quad d is not above this is skipped: its range is undefined or so ill
conditioned (a ray along a Gaussian 10^6 times longer than thin) that it means nothing, and
this bound keeps t* and its gradient finite in float32."""


@dataclasses.dataclass
class SphericalSplats:
    """Gaussians on the sensor's sphere (module docstring). The first six are differentiable.

    Attributes:
        azimuth: (N,) degrees in [0, 360).
        elevation: (N,) degrees.
        conics: (N, 3) inverse angular covariance (a, b, c) = [[a, b], [b, c]], degrees^-2,
            over (azimuth, elevation).
        opacities: (N,).
        quad: (N, 6) S^-1 / max(S^-1 eigenvalue) in the sensor frame: xx, xy, xz, yy, yz, zz.
        lin: (N, 3) quad @ m.
        distance: (N,) centre distance |m| in metres (compositing order).
        extent: (N, 2) angular half-extents (azimuth, elevation) in degrees of alpha >= 1/255.
        visible: (N,) bool, False for Gaussians not drawn.
    """

    azimuth: torch.Tensor
    elevation: torch.Tensor
    conics: torch.Tensor
    opacities: torch.Tensor
    quad: torch.Tensor
    lin: torch.Tensor
    distance: torch.Tensor
    extent: torch.Tensor
    visible: torch.Tensor


def wrap_degrees(x: torch.Tensor) -> torch.Tensor:
    """Angles in degrees (any shape) -> the same angles in [-180, 180)."""
    return torch.remainder(x + 180.0, 360.0) - 180.0


def ray_directions(azimuth_deg: torch.Tensor, elevation_deg: torch.Tensor) -> torch.Tensor:
    """(R,) azimuths and (R,) elevations in degrees -> (R, 3) unit directions in the sensor frame."""
    a, e = torch.deg2rad(azimuth_deg), torch.deg2rad(elevation_deg)
    return torch.stack([torch.cos(e) * torch.cos(a), torch.cos(e) * torch.sin(a), torch.sin(e)], -1)


def max_response_range(quad: torch.Tensor, lin: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Range of maximum response t* = d^T Q m / d^T Q d of Gaussians on rays.

    quad (..., 6) and lin (..., 3) as in :class:`SphericalSplats`, dirs (..., 3) unit ray
    directions, broadcast together -> t* (...,) metres and ``defined`` (...,) bool, False
    where d^T Q d <= :data:`MIN_RANGE_DENOMINATOR` (t* is then 0, with finite gradients)."""
    dx, dy, dz = dirs.unbind(-1)
    qxx, qxy, qxz, qyy, qyz, qzz = quad.unbind(-1)
    den = qxx * dx * dx + qyy * dy * dy + qzz * dz * dz + 2.0 * (qxy * dx * dy + qxz * dx * dz + qyz * dy * dz)
    defined = den > MIN_RANGE_DENOMINATOR
    num = (lin * dirs).sum(-1)
    return torch.where(defined, num, torch.zeros_like(num)) / torch.where(defined, den, torch.ones_like(den)), defined


@dataclasses.dataclass(frozen=True)
class SphereTiles:
    """Tiles of the sensor's sphere that bin rays and Gaussians: ``columns`` azimuth columns
    of ``column_deg`` from azimuth 0, ``rows`` elevation rows of ``row_deg`` from
    ``first_elevation`` (the lowest ray's), so that every ray falls in one tile
    (``row * columns + column``)."""

    columns: int
    rows: int
    column_deg: float
    row_deg: float
    first_elevation: float

    @property
    def count(self) -> int:
        return self.columns * self.rows

    @classmethod
    def for_rays(cls, rays: LidarRays, rays_per_tile: int = 64) -> "SphereTiles":
        """Square tiles (in degrees) holding about ``rays_per_tile`` rays each if the rays
        spread evenly over the elevation band they span and the whole degrees of azimuth
        they occupy."""
        el = rays.elevation_deg.detach().to(torch.float64)
        if len(el) == 0:
            return cls(1, 1, 360.0, 180.0, -90.0)
        lo, hi = float(el.min()), float(el.max())
        band = max(hi - lo, 1e-3)
        degrees = torch.remainder(rays.azimuth_deg.detach().to(torch.float64), 360.0).long().clamp(0, 359)
        occupied = int((torch.bincount(degrees, minlength=360) > 0).sum())
        side = math.sqrt(occupied * band * rays_per_tile / len(el))
        columns = int(min(max(round(360.0 / side), 1), 4096))
        row_deg = min(max(side, 1e-3), 180.0)
        return cls(columns, int((hi - lo) // row_deg) + 1, 360.0 / columns, row_deg, lo)

    def of_rays(self, rays: LidarRays) -> torch.Tensor:
        """(R,) int64 tile of each ray."""
        az = torch.remainder(rays.azimuth_deg.detach().to(torch.float64), 360.0)
        col = torch.floor(az / self.column_deg).long().clamp(0, self.columns - 1)
        row = torch.floor((rays.elevation_deg.detach().to(torch.float64) - self.first_elevation) / self.row_deg)
        return row.long().clamp(0, self.rows - 1) * self.columns + col

    def boxes(self, proj: SphericalSplats) -> torch.Tensor:
        """(N, 4) int64 tile box of each Gaussian: first column, number of columns (taken
        modulo ``columns``: a box may wrap past azimuth 360), first row, number of rows (0
        for a Gaussian not drawn or out of the rays' elevation band)."""
        with torch.no_grad():
            az = proj.azimuth.detach().to(torch.float64)
            el = proj.elevation.detach().to(torch.float64)
            ext = proj.extent.to(torch.float64)
            c0 = torch.floor((az - ext[:, 0]) / self.column_deg)
            c1 = torch.floor((az + ext[:, 0]) / self.column_deg)
            ncol = torch.clamp(c1 - c0 + 1, max=self.columns)
            r0 = torch.floor((el - ext[:, 1] - self.first_elevation) / self.row_deg).clamp(min=0)
            r1 = torch.floor((el + ext[:, 1] - self.first_elevation) / self.row_deg).clamp(max=self.rows - 1)
            nrow = torch.where(proj.visible, (r1 - r0 + 1).clamp(min=0), torch.zeros_like(r1))
            return torch.stack([torch.remainder(c0, self.columns), ncol, r0.clamp(max=self.rows), nrow], -1).long()


def project_lidar(splats: Splats, rays: LidarRays, eps_deg2: float) -> SphericalSplats:
    """Project (N,) Gaussians to the sphere of the sensor at ``rays.sensor_to_world``
    (module docstring); differentiable in the splats (not in the pose)."""
    means, quats, scales, opacities = splats.means, splats.quats, splats.scales, splats.opacities
    dtype = means.dtype
    pose = rays.sensor_to_world.detach().to(dtype)
    Rs, ts = pose[:3, :3], pose[:3, 3]
    m = (means - ts) @ Rs  # (N, 3) sensor frame: Rs^T (mu - t)
    x, y, z = m.unbind(-1)
    rxy2 = x * x + y * y
    rho2 = rxy2 + z * z
    with torch.no_grad():
        rho = torch.sqrt(rho2)
        visible = ((rho > rays.min_range) & (rho < rays.max_range)
                   & (torch.sqrt(rxy2) > rho * math.sin(math.radians(POLE_MARGIN_DEG)))
                   & (opacities >= ALPHA_THRESHOLD))
    # undrawn Gaussians get a harmless stand-in mean, so that no NaN enters the graph
    one = torch.ones_like(x)
    xs, ys, zs = torch.where(visible, x, one), torch.where(visible, y, 0 * one), torch.where(visible, z, 0 * one)
    rxy2 = xs * xs + ys * ys
    rho2 = rxy2 + zs * zs
    rxy = torch.sqrt(rxy2)
    deg = 180.0 / math.pi
    azimuth = torch.remainder(torch.rad2deg(torch.atan2(ys, xs)), 360.0)
    elevation = torch.rad2deg(torch.atan2(zs, rxy))
    zero = torch.zeros_like(xs)
    J = deg * torch.stack([-ys / rxy2, xs / rxy2, zero,
                           -xs * zs / (rho2 * rxy), -ys * zs / (rho2 * rxy), rxy / rho2], -1).reshape(-1, 2, 3)
    rot = Rs.T @ quat_to_rotmat(quats)  # (N, 3, 3) Gaussian axes in the sensor frame
    M = rot * scales[:, None, :]
    JM = J @ M
    conics, diag, _, ok = lowpass_conics(JM @ JM.transpose(1, 2), eps_deg2, visible)  # degrees^2 before inverting

    s = scales.clamp_min(MIN_SCALE)
    weight = (s.min(-1, keepdim=True).values / s) ** 2  # (N, 3) in (0, 1]: S^-1 scaled by the smallest variance
    Q = (rot * weight[:, None, :]) @ rot.transpose(1, 2)  # (N, 3, 3)
    quad = torch.stack([Q[:, 0, 0], Q[:, 0, 1], Q[:, 0, 2], Q[:, 1, 1], Q[:, 1, 2], Q[:, 2, 2]], -1)
    lin = (Q @ torch.stack([xs, ys, zs], -1)[..., None])[..., 0]

    with torch.no_grad():
        level = 2.0 * torch.log(torch.clamp(opacities / ALPHA_THRESHOLD, min=1.0))  # alpha >= 1/255 inside
        extent = EXTENT_MARGIN[0] * torch.sqrt(level[:, None] * diag.clamp_min(0.0))
        extent = extent + EXTENT_MARGIN[1]
        extent = torch.nan_to_num(extent, nan=360.0, posinf=360.0).clamp(max=360.0)  # an overflow covers all
        extent = torch.where(ok[:, None], extent, torch.zeros_like(extent))
    return SphericalSplats(azimuth, elevation, conics, opacities, quad, lin, torch.sqrt(rho2).detach(), extent, ok)


REACH_MARGIN = (1.02, 0.01)
""":func:`may_reach` widens its bound by 2% and 0.01 degrees over the projection's own
extents (:data:`EXTENT_MARGIN`), so float32 rounding in a backend never keeps a pair it culls."""


def ray_arc(azimuth_deg: torch.Tensor) -> tuple[float, float]:
    """(R,) azimuths in degrees (R >= 1) -> (start, length): the shortest arc of azimuth,
    counter-clockwise from ``start`` in [0, 360) over ``length`` degrees, holding every ray."""
    az = torch.sort(torch.remainder(azimuth_deg.detach().to(torch.float64), 360.0)).values
    gaps = torch.diff(az, append=az[:1] + 360.0)  # gap after each ray, the last one wrapping
    widest = int(torch.argmax(gaps))
    start = float(az[(widest + 1) % len(az)])
    return start, 360.0 - float(gaps[widest])


def may_reach(means: torch.Tensor, log_scales: torch.Tensor, rays: LidarRays, eps_deg2: float) -> torch.Tensor:
    """(N,) bool: False for Gaussians whose alpha is below 1/255 on every ray of ``rays``
    whatever their opacity and rotation, so that leaving them out renders the same sweep with
    the same gradients (the others get none from it). ``means`` (N, 3) world, ``log_scales``
    (N, 3) (scales before ``exp``).

    The bound: the projected angular variance along azimuth is at most
    (180/pi)^2 s_max^2 / rho^2 + eps_deg2 (the azimuth row of the Jacobian has norm
    (180/pi) / rho, rho the horizontal distance; s_max the largest scale), along elevation
    the same with the centre distance, and alpha >= 1/255 needs the angular offset within
    sqrt(2 ln 255) standard deviations (opacity <= 1). A Gaussian is kept when that
    half-width reaches the shortest arc of the rays' azimuths (:func:`ray_arc`) and the band
    of their elevations."""
    R = len(rays)
    if R == 0:
        return torch.zeros(len(means), dtype=torch.bool, device=means.device)
    with torch.no_grad():
        means = means.detach()
        pose = rays.sensor_to_world.detach().to(means.dtype)
        x, y, z = ((means - pose[:3, 3]) @ pose[:3, :3]).unbind(-1)  # sensor frame
        rho2 = x * x + y * y
        # squared half-widths over (180/pi)^2: k^2 (s^2 / d^2 + eps'), s the largest scale
        k2 = (REACH_MARGIN[0] * EXTENT_MARGIN[0]) ** 2 * 2.0 * math.log(1.0 / ALPHA_THRESHOLD)
        s2 = torch.exp(2.0 * log_scales.detach().max(-1).values)
        eps = eps_deg2 * (math.pi / 180.0) ** 2
        pad = EXTENT_MARGIN[1] + REACH_MARGIN[1]

        def half_width(d2: torch.Tensor) -> torch.Tensor:
            w = torch.rad2deg(torch.sqrt(k2 * (s2 / d2 + eps))) + pad
            return torch.nan_to_num(w, nan=math.inf)

        start, length = ray_arc(rays.azimuth_deg)
        offset = torch.remainder(torch.rad2deg(torch.atan2(y, x)) - start, 360.0)  # from the arc's start
        off_arc = torch.minimum(offset - length, 360.0 - offset)  # <= 0 on the arc
        keep = off_arc <= half_width(rho2)
        el = torch.rad2deg(torch.atan2(z, torch.sqrt(rho2)))
        lo = float(rays.elevation_deg.detach().min())
        hi = float(rays.elevation_deg.detach().max())
        reach_el = half_width(rho2 + z * z)
        return keep & (el >= lo - reach_el) & (el <= hi + reach_el)
