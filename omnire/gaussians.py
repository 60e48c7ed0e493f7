"""Gaussian sets: raw parameters, activation, SE(3) transforms, concatenation, SH colour.

Raw storage (docs/conventions.md, "Gaussians"): means (N,3), quats (N,4) wxyz un-normalised, log-scales
(N,3), opacity logits (N,), SH coefficients sh0 (N,1,3) and shN (N,K-1,3) with
K = (degree+1)^2, degree <= 3.
"""
from __future__ import annotations

import dataclasses
import math

import torch

from omnire.geometry import quat_left_matrix, quat_multiply, rotmat_to_quat

SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)
GAUSSIAN_KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """(N, 3) colour in [0,1] -> (N, 1, 3) DC coefficient."""
    return ((rgb - 0.5) / SH_C0)[:, None, :]


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics up to ``degree`` (0..3).

    coeffs: (N, K, C) with K >= (degree+1)^2; dirs: (N, 3) unit view directions.
    Returns (N, C).
    """
    out = SH_C0 * coeffs[:, 0]
    if degree < 1:
        return out
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    out = out - _SH_C1 * y * coeffs[:, 1] + _SH_C1 * z * coeffs[:, 2] - _SH_C1 * x * coeffs[:, 3]
    if degree < 2:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (
        out
        + _SH_C2[0] * xy * coeffs[:, 4]
        + _SH_C2[1] * yz * coeffs[:, 5]
        + _SH_C2[2] * (2 * zz - xx - yy) * coeffs[:, 6]
        + _SH_C2[3] * xz * coeffs[:, 7]
        + _SH_C2[4] * (xx - yy) * coeffs[:, 8]
    )
    if degree < 3:
        return out
    return (
        out
        + _SH_C3[0] * y * (3 * xx - yy) * coeffs[:, 9]
        + _SH_C3[1] * xy * z * coeffs[:, 10]
        + _SH_C3[2] * y * (4 * zz - xx - yy) * coeffs[:, 11]
        + _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[:, 12]
        + _SH_C3[4] * x * (4 * zz - xx - yy) * coeffs[:, 13]
        + _SH_C3[5] * z * (xx - yy) * coeffs[:, 14]
        + _SH_C3[6] * x * (xx - 3 * yy) * coeffs[:, 15]
    )


@dataclasses.dataclass
class Gaussians:
    """A set of N Gaussians in raw parameterisation (see module docstring).

    Instances are cheap views of node parameters; transforms return new instances and keep
    autograd connections to the originals.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh0: torch.Tensor
    shN: torch.Tensor

    def __len__(self) -> int:
        return self.means.shape[0]

    @classmethod
    def from_params(cls, params: "torch.nn.ParameterDict | dict[str, torch.Tensor]", rows: torch.Tensor | None = None) -> "Gaussians":
        """Build from a node's parameter dict (keys :data:`GAUSSIAN_KEYS`), optionally a row subset."""
        vals = [params[k] for k in GAUSSIAN_KEYS]
        if rows is not None:
            vals = [v[rows] for v in vals]
        return cls(*vals)

    @property
    def activated_scales(self) -> torch.Tensor:
        return torch.exp(self.scales)

    @property
    def activated_opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacities)

    @property
    def sh_degree(self) -> int:
        return int(math.isqrt(1 + self.shN.shape[1])) - 1

    def transform(self, rotation: torch.Tensor, translation: torch.Tensor) -> "Gaussians":
        """Apply x -> R x + t. ``rotation`` is (3,3) or per-Gaussian (N,3,3); ``translation``
        (3,) or (N,3). Rotations of the Gaussians compose as q' = quat(R) * q.
        SH coefficients are not rotated (view directions are evaluated in world space by
        callers that need it; for rigid actors the error is second order and the
        reference implementation makes the same choice)."""
        if rotation.ndim == 2:  # one rotation for all: two matrix products (forward and backward)
            means = torch.addmm(translation.expand_as(self.means), self.means, rotation.T)
            quats = self.quats @ quat_left_matrix(rotmat_to_quat(rotation)).T
        else:
            means = torch.einsum("nij,nj->ni", rotation, self.means) + translation
            quats = quat_multiply(rotmat_to_quat(rotation), self.quats)
        return dataclasses.replace(self, means=means, quats=quats)

    def subset(self, rows: torch.Tensor) -> "Gaussians":
        """The Gaussians at ``rows`` (M,) (autograd flows back to the full set)."""
        return Gaussians(*(getattr(self, f.name)[rows] for f in dataclasses.fields(self)))

    @staticmethod
    def cat(parts: list["Gaussians"]) -> "Gaussians":
        """Concatenate; SH bands are zero-padded to the largest degree present."""
        if len(parts) == 1:
            return parts[0]
        k = max(p.shN.shape[1] for p in parts)
        shN = [
            p.shN if p.shN.shape[1] == k else torch.cat([p.shN, p.shN.new_zeros(len(p), k - p.shN.shape[1], 3)], 1)
            for p in parts
        ]
        return Gaussians(
            means=torch.cat([p.means for p in parts]),
            quats=torch.cat([p.quats for p in parts]),
            scales=torch.cat([p.scales for p in parts]),
            opacities=torch.cat([p.opacities for p in parts]),
            sh0=torch.cat([p.sh0 for p in parts]),
            shN=torch.cat(shN),
        )

    def colors(self, camera_center: torch.Tensor, degree: int) -> torch.Tensor:
        """(N, 3) RGB seen from ``camera_center`` (3,), using SH bands up to ``degree``."""
        degree = min(degree, self.sh_degree)
        coeffs = torch.cat([self.sh0, self.shN], 1) if degree > 0 else self.sh0
        dirs = self.means.detach() - camera_center
        dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)
