"""First hits of rays on a triangle mesh, with trimesh's Embree backend (``embreex``).

Embree finds the first triangle along each ray in float32; the distance is then recomputed
in float64 as the distance along the ray to that triangle's plane, so a hit lies on the
mesh to rounding. Used by the synthetic generator's LiDAR and the LiDAR mesh baseline
(:mod:`omnire.lidar_baselines`).
"""
from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class RayHits:
    """The first hit of each of R rays.

    Attributes:
        face: (R,) int64 first triangle hit, -1 where the ray hits nothing.
        distance: (R,) float64 metres along the (unit) ray, NaN where nothing is hit.
        cos_incidence: (R,) float64 |cos| of the angle between the ray and the triangle's
            normal (1 = head-on), NaN where nothing is hit.
    """

    face: np.ndarray
    distance: np.ndarray
    cos_incidence: np.ndarray


def first_hits(verts: np.ndarray, faces: np.ndarray, origins: np.ndarray, directions: np.ndarray) -> RayHits:
    """First triangle along each ray.

    Args:
        verts: (V, 3) vertices; faces: (Fc, 3) vertex indices (Fc may be 0).
        origins: (R, 3) ray origins; directions: (R, 3) unit directions (same frame as verts).
    """
    verts = np.asarray(verts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    R = len(directions)
    if origins.shape != (R, 3) or directions.shape != (R, 3):
        raise ValueError(f"first_hits: origins {origins.shape} and directions {directions.shape}; expected (R, 3) each")
    face = np.full(R, -1, dtype=np.int64)
    distance = np.full(R, np.nan)
    cos_incidence = np.full(R, np.nan)
    if len(faces) == 0 or R == 0:
        return RayHits(face, distance, cos_incidence)
    import trimesh  # here, not at the top: omnire.api stays light for plugins that never cast rays
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    mesh = trimesh.Trimesh(verts, faces, process=False, validate=False)
    tri, ray = RayMeshIntersector(mesh).intersects_id(origins, directions, multiple_hits=False)
    tri, ray = np.asarray(tri, dtype=np.int64), np.asarray(ray, dtype=np.int64)
    v = verts[faces[tri]]  # (H, 3, 3)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-300)
    cos = np.abs((n * directions[ray]).sum(1))
    face[ray] = tri
    distance[ray] = np.abs(((v[:, 0] - origins[ray]) * n).sum(1)) / cos.clip(1e-300)  # to the plane, float64
    cos_incidence[ray] = cos
    return RayHits(face, distance, cos_incidence)
