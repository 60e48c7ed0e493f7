"""Ground-truth LiDAR: a spinning sensor's sweep ray-traced through the scene's triangles
with trimesh's Embree backend (``embreex``, through ``omnire.api.first_hits``: a return
lies on the mesh to rounding).

A ray returns nothing (a missing return, recorded with its reason) when it hits nothing,
when its hit is beyond the beam model's max range or nearer than its min range,
or when it meets the surface at a grazing angle (incidence from the normal above
``grazing_drop_deg``). Intensity: the hit material's reflectivity times
``0.3 + 0.7 cos(incidence)`` (Lambertian with an ambient floor), in [0, 1].
"""
from __future__ import annotations

import dataclasses

import numpy as np

from omnire.api import BeamModel, first_hits

RETURNED, NOTHING_HIT, OUT_OF_RANGE, GRAZING = 0, 1, 2, 3
"""Why a ray did or did not return (:attr:`Sweep.reason`)."""


@dataclasses.dataclass(frozen=True)
class LidarSpec:
    """A simulated sensor: its beam model, what each material reflects, when rays drop.

    Attributes:
        beams: the :class:`BeamModel` (elevations, azimuth step, range limits).
        reflectivity: (M,) reflectivity in [0, 1] of material id m (the meshes' ``mat``).
        grazing_drop_deg: rays meeting a surface further than this from its normal return
            nothing (90 keeps every hit).
    """

    beams: BeamModel
    reflectivity: np.ndarray
    grazing_drop_deg: float = 85.0


@dataclasses.dataclass
class Sweep:
    """Every ray of one revolution (R = beams x azimuth bins, beam-major).

    Attributes:
        direction: (R, 3) unit rays in the sensor frame (x forward, y left, z up).
        beam, column: (R,) beam index and azimuth bin of each ray.
        range: (R,) float64 metres, NaN where nothing returned.
        face: (R,) int64 first triangle hit (-1 when none; set also for dropped hits).
        intensity: (R,) float32 in [0, 1], NaN where nothing returned.
        reason: (R,) int8: RETURNED, NOTHING_HIT, OUT_OF_RANGE or GRAZING.
    """

    direction: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    range: np.ndarray
    face: np.ndarray
    intensity: np.ndarray
    reason: np.ndarray

    @property
    def returned(self) -> np.ndarray:
        return self.reason == RETURNED

    def points_sensor(self) -> np.ndarray:
        """(P, 3) sensor-frame points of the returns."""
        ok = self.returned
        return self.direction[ok] * self.range[ok, None]


def cast_sweep(verts: np.ndarray, faces: np.ndarray, material: np.ndarray, sensor_to_world: np.ndarray,
               spec: LidarSpec) -> Sweep:
    """Ray-trace one sweep from ``sensor_to_world`` (4, 4) through a triangle mesh.

    Args:
        verts: (V, 3) world vertices; faces: (Fc, 3) vertex indices; material: (Fc,) ids
            into ``spec.reflectivity``.
    """
    verts = np.asarray(verts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    d_s, beam, column = spec.beams.directions()
    R = len(d_s)
    rng = np.full(R, np.nan)
    face = np.full(R, -1, dtype=np.int64)
    intensity = np.full(R, np.nan, dtype=np.float32)
    reason = np.full(R, NOTHING_HIT, dtype=np.int8)
    rot, origin = sensor_to_world[:3, :3], sensor_to_world[:3, 3]
    hits = first_hits(verts, faces, np.broadcast_to(origin, (R, 3)), d_s @ rot.T)
    ray = np.flatnonzero(hits.face >= 0)
    tri, dist, cos = hits.face[ray], hits.distance[ray], hits.cos_incidence[ray]
    face[ray] = tri
    ok_range = (dist >= spec.beams.min_range) & (dist <= spec.beams.max_range)
    ok_angle = cos >= np.cos(np.deg2rad(spec.grazing_drop_deg))
    reason[ray] = np.where(~ok_range, OUT_OF_RANGE, np.where(~ok_angle, GRAZING, RETURNED))
    keep = ok_range & ok_angle
    hit = ray[keep]
    rng[hit] = dist[keep]
    refl = np.asarray(spec.reflectivity, dtype=np.float64)[np.asarray(material)[tri[keep]]]
    intensity[hit] = (refl * (0.3 + 0.7 * cos[keep])).astype(np.float32)
    return Sweep(d_s, beam, column, rng, face, intensity, reason)
