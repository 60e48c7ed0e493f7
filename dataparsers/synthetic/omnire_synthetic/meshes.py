"""Textured triangle meshes and the primitives the street is built from (numpy float64)."""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from omnire.api import axis_rotation


@dataclasses.dataclass
class Mesh:
    """verts (V, 3); faces (F, 3) int64; uv (V, 2) in texture repeats; mat (F,) material ids."""

    verts: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    mat: np.ndarray

    @staticmethod
    def empty() -> "Mesh":
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 2)), np.zeros(0, np.int64))

    @staticmethod
    def concat(parts: Sequence["Mesh"]) -> "Mesh":
        parts = [p for p in parts if p.faces.shape[0]]
        if not parts:
            return Mesh.empty()
        offs = np.cumsum([0] + [p.verts.shape[0] for p in parts[:-1]])
        return Mesh(
            np.concatenate([p.verts for p in parts]),
            np.concatenate([p.faces + o for p, o in zip(parts, offs)]),
            np.concatenate([p.uv for p in parts]),
            np.concatenate([p.mat for p in parts]),
        )

    def transformed(self, T: np.ndarray) -> "Mesh":
        """Apply a (4, 4) rigid transform to the vertices."""
        return Mesh(self.verts @ T[:3, :3].T + T[:3, 3], self.faces, self.uv, self.mat)


def quad(corners: np.ndarray, mat: int, uv_size: tuple[float, float], nu: int = 1, nv: int = 1) -> Mesh:
    """A planar quad p0 -> p1 (u direction) -> p2 -> p3, split into nu x nv cells.

    ``uv_size`` is the physical size (metres) of one texture repeat along u and v.
    """
    p0, p1, p2, p3 = (np.asarray(c, dtype=np.float64) for c in corners)
    s = np.linspace(0.0, 1.0, nu + 1)
    t = np.linspace(0.0, 1.0, nv + 1)
    S, Tt = np.meshgrid(s, t, indexing="xy")  # (nv+1, nu+1)
    S, Tt = S[..., None], Tt[..., None]
    verts = (1 - S) * (1 - Tt) * p0 + S * (1 - Tt) * p1 + S * Tt * p2 + (1 - S) * Tt * p3
    len_u = np.linalg.norm(p1 - p0)
    len_v = np.linalg.norm(p3 - p0)
    uv = np.concatenate([S * len_u / uv_size[0], Tt * len_v / uv_size[1]], -1)
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nv + 1, nu + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(verts.reshape(-1, 3), faces.astype(np.int64), uv.reshape(-1, 2), np.full(len(faces), mat, np.int64))


def box(size: Sequence[float], mats, uv_size: float = 1.0, bottom: bool = False,
        facade_uv: tuple[float, float] | None = None) -> Mesh:
    """Axis-aligned box centred at the origin, size (lx, ly, lz).

    ``mats`` is one material or a dict with keys ``side``, ``top``, ``bottom``, ``front``
    (+x face), ``back``. ``facade_uv`` gives (width, height) of one texture repeat on the
    sides with v running down from the top edge (for window grids).
    """
    lx, ly, lz = (s / 2.0 for s in size)
    m = mats if isinstance(mats, dict) else {"side": mats, "top": mats, "bottom": mats}
    side = m["side"]
    sides = {
        "front": [(lx, -ly, lz), (lx, ly, lz), (lx, ly, -lz), (lx, -ly, -lz)],
        "back": [(-lx, ly, lz), (-lx, -ly, lz), (-lx, -ly, -lz), (-lx, ly, -lz)],
        "left": [(lx, ly, lz), (-lx, ly, lz), (-lx, ly, -lz), (lx, ly, -lz)],
        "right": [(-lx, -ly, lz), (lx, -ly, lz), (lx, -ly, -lz), (-lx, -ly, -lz)],
    }
    parts = []
    for name, c in sides.items():
        uvs = facade_uv if facade_uv else (uv_size, uv_size)
        parts.append(quad(c, m.get(name, side), uvs))
    parts.append(quad([(-lx, -ly, lz), (lx, -ly, lz), (lx, ly, lz), (-lx, ly, lz)], m.get("top", side), (uv_size, uv_size)))
    if bottom:
        parts.append(quad([(-lx, ly, -lz), (lx, ly, -lz), (lx, -ly, -lz), (-lx, -ly, -lz)], m.get("bottom", side), (uv_size, uv_size)))
    return Mesh.concat(parts)


def prism(radius: float, height: float, mat: int, n: int = 8, cap_mat: int | None = None,
          uv_size: tuple[float, float] = (1.0, 1.0), caps: bool = True) -> Mesh:
    """Upright n-gon prism, base at z = 0, axis +z, radius to the vertices."""
    ang = np.linspace(0.0, 2 * np.pi, n + 1)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], 1)  # (n+1, 2) closed
    circ = 2 * np.pi * radius
    verts, uv = [], []
    for z, v in ((0.0, height / uv_size[1]), (height, 0.0)):
        verts.append(np.concatenate([ring, np.full((n + 1, 1), z)], 1))
        uv.append(np.stack([np.linspace(0, circ / uv_size[0], n + 1), np.full(n + 1, v)], 1))
    verts, uv = np.concatenate(verts), np.concatenate(uv)
    i = np.arange(n)
    faces = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    mats = np.full(len(faces), mat, np.int64)
    side = Mesh(verts, faces.astype(np.int64), uv, mats)
    if not caps:
        return side
    cm = mat if cap_mat is None else cap_mat
    cap_parts = []
    for z in (0.0, height):
        cv = np.concatenate([[[0.0, 0.0, z]], np.concatenate([ring[:-1], np.full((n, 1), z)], 1)])
        cuv = 0.5 + 0.5 * np.concatenate([[[0.0, 0.0]], ring[:-1] / radius])
        cf = np.stack([np.zeros(n, np.int64), 1 + i, 1 + (i + 1) % n], 1)
        cap_parts.append(Mesh(cv, cf, cuv, np.full(n, cm, np.int64)))
    return Mesh.concat([side] + cap_parts)


def ellipsoid(radii: Sequence[float], mat: int, n_lat: int = 8, n_lon: int = 12, uv_size: float = 1.0) -> Mesh:
    """Lat-long ellipsoid centred at the origin."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    lon = np.linspace(0.0, 2 * np.pi, n_lon + 1)
    LA, LO = np.meshgrid(lat, lon, indexing="ij")  # (n_lat+1, n_lon+1)
    r = np.asarray(radii, dtype=np.float64)
    verts = np.stack([np.cos(LA) * np.cos(LO), np.cos(LA) * np.sin(LO), np.sin(LA)], -1) * r
    uv = np.stack([LO * r[0] / uv_size, (LA + np.pi / 2) * r[2] / uv_size], -1)
    idx = np.arange((n_lat + 1) * (n_lon + 1)).reshape(n_lat + 1, n_lon + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)
    return Mesh(verts.reshape(-1, 3), faces, uv.reshape(-1, 2), np.full(len(faces), mat, np.int64))


def rot_z(a: float) -> np.ndarray:
    """(3, 3) rotation by ``a`` radians about z (see :func:`omnire.geometry.axis_rotation`)."""
    return axis_rotation(2, float(a))


def rot_x(a: float) -> np.ndarray:
    """(3, 3) rotation by ``a`` radians about x."""
    return axis_rotation(0, float(a))
