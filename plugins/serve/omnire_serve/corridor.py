"""The route and the drivable corridor of a log, from the recorded ego path and the LiDAR.

The *route* is the recorded ego (rig) path projected on the ground plane: a polyline with
its arc length. The *corridor* is the route widened to each side, station by station
(every ``spacing`` metres along it): at a station, the LiDAR points of every sweep within
half a spacing along the route are taken (points inside any actor's box at that sweep's
frame, grown by 0.3 m, are dropped: actors are checked by their boxes, not here); the ground
height there is the median height of the points within 1.5 m of the path below the rig (the
road under the car), and the corridor's border on each side is the nearest point that stands
between ``obstacle_low`` and ``obstacle_high`` metres above that ground (a kerb high enough,
a wall, a pole, a parked object), capped at ``max_half_width`` and never narrower than
``min_half_width``. A station without ground points takes the previous station's ground.

Shapes: rig poses (F, 4, 4) world, x forward, y left, z up; LiDAR sweeps (N_f, 3) world.
"""
from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

from omnire.api import points_in_box


@dataclasses.dataclass(frozen=True)
class Corridor:
    """Stations along the route. ``xy`` (K, 2) route points at arc lengths ``s`` (K,),
    ``left`` / ``right`` (K,) metres of drivable width to each side (positive), ``ground``
    (K,) ground height. ``length``: the route's length in metres."""

    xy: np.ndarray
    s: np.ndarray
    left: np.ndarray
    right: np.ndarray
    ground: np.ndarray

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def project(self, point: np.ndarray) -> tuple[float, float]:
        """(arc length s, signed distance d, left positive) of the nearest point of the
        route polyline to ``point`` (2,). Beyond the ends, s runs on along the end segments
        (negative before the start, above ``length`` past the end)."""
        p = np.asarray(point, dtype=np.float64)[:2]
        a, b = self.xy[:-1], self.xy[1:]
        seg = b - a
        seg_len = np.linalg.norm(seg, axis=1)
        u = seg / seg_len[:, None]
        rel = p - a
        along = np.einsum("ij,ij->i", rel, u)
        clamped = np.clip(along, 0.0, seg_len)
        first, last = 0, len(seg) - 1
        clamped[first] = min(along[first], seg_len[first])  # runs on before the start
        clamped[last] = max(along[last], 0.0)  # and past the end
        foot = a + clamped[:, None] * u
        dist = np.linalg.norm(p - foot, axis=1)
        k = int(np.argmin(dist))
        side = u[k, 0] * rel[k, 1] - u[k, 1] * rel[k, 0]
        return float(self.s[k] + clamped[k]), float(np.copysign(dist[k], side))

    def width_at(self, s: float) -> tuple[float, float]:
        """(left, right) drivable widths at arc length ``s`` (held beyond the ends)."""
        return float(np.interp(s, self.s, self.left)), float(np.interp(s, self.s, self.right))

    def point_at(self, s: float) -> np.ndarray:
        """(2,) the route point at arc length ``s`` (clamped to the route)."""
        return np.array([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])])

    def heading_at(self, s: float) -> float:
        """The route's heading (radians) at arc length ``s``."""
        return arc_heading(self.xy, self.s, s)

    def as_json(self) -> dict:
        r = lambda a: np.round(a, 4).tolist()  # noqa: E731
        return {"xy": r(self.xy), "s": r(self.s), "left": r(self.left), "right": r(self.right),
                "ground": r(self.ground)}

    @classmethod
    def from_json(cls, data: dict) -> "Corridor":
        return cls(*(np.asarray(data[k], dtype=np.float64) for k in ("xy", "s", "left", "right", "ground")))


def route_polyline(rig_to_world: np.ndarray) -> np.ndarray:
    """(K, 2) the rig path on the ground plane without standing points (see
    :func:`moving_indices`)."""
    keep = moving_indices(rig_to_world)
    if len(keep) < 2:
        raise ValueError("the recorded ego path does not move: no route to drive")
    return np.asarray(rig_to_world, dtype=np.float64)[keep, :2, 3]


def moving_indices(rig_to_world: np.ndarray, min_step: float = 0.05) -> list[int]:
    """Frames of the rig path kept for the route: each at least ``min_step`` metres (on the
    ground plane) from the previous one kept."""
    xy = np.asarray(rig_to_world, dtype=np.float64)[:, :2, 3]
    keep = [0]
    for i in range(1, len(xy)):
        if np.linalg.norm(xy[i] - xy[keep[-1]]) >= min_step:
            keep.append(i)
    return keep


def build_corridor(rig_to_world: np.ndarray, sweeps: Sequence[Optional[np.ndarray]],
                   boxes: Sequence[Sequence[tuple[np.ndarray, np.ndarray]]], spacing: float = 1.0,
                   max_half_width: float = 3.5, min_half_width: float = 1.2, obstacle_low: float = 0.3,
                   obstacle_high: float = 2.5) -> Corridor:
    """The corridor (see the module docstring). ``sweeps``: per frame (N_f, 3) world LiDAR
    points or None; ``boxes``: per frame the actor boxes present, each (pose (4, 4), size
    (3,)), whose points are dropped."""
    route = route_polyline(rig_to_world)
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, arc[-1], spacing)
    s = np.append(s, arc[-1]) if arc[-1] - s[-1] > 1e-6 else s
    xy = np.stack([np.interp(s, arc, route[:, 0]), np.interp(s, arc, route[:, 1])], 1)
    rig_z = np.interp(s, arc, np.asarray(rig_to_world)[moving_indices(rig_to_world), 2, 3])
    pts = []
    for f, p in enumerate(sweeps):
        if p is None or len(p) == 0:
            continue
        p = np.asarray(p, dtype=np.float64)
        keep = np.ones(len(p), bool)
        for pose, size in boxes[f] if f < len(boxes) else ():
            keep &= ~points_in_box(p, pose, np.asarray(size, dtype=np.float64), margin=0.3)
        pts.append(p[keep])
    cloud = np.concatenate(pts) if pts else np.zeros((0, 3))
    K = len(s)
    left, right, ground = np.full(K, max_half_width), np.full(K, max_half_width), np.zeros(K)
    last_ground = None
    for k in range(K):
        a = arc_heading(route, arc, s[k])
        t, n = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        rel = cloud[:, :2] - xy[k]
        along, lat = rel @ t, rel @ n
        near = np.abs(along) <= spacing / 2 + 0.5
        z = cloud[near, 2]
        lat_n = lat[near]
        road = z[(np.abs(lat_n) < 1.5) & (z < rig_z[k])]
        if len(road):
            g = float(np.median(road))
        elif last_ground is not None:
            g = last_ground
        else:
            g = float(np.percentile(z, 10)) if len(z) else rig_z[k]
        last_ground = ground[k] = g
        obstacle = (z > g + obstacle_low) & (z < g + obstacle_high)
        lo = lat_n[obstacle]
        if np.any(lo > 0):
            left[k] = min(max_half_width, float(lo[lo > 0].min()))
        if np.any(lo < 0):
            right[k] = min(max_half_width, float(-lo[lo < 0].max()))
    left, right = np.maximum(left, min_half_width), np.maximum(right, min_half_width)
    return Corridor(xy, s, left, right, ground)


def arc_heading(route: np.ndarray, arc: np.ndarray, s: float) -> float:
    """The heading (radians) of the route segment at arc length ``s``."""
    k = int(np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(route) - 2))
    d = route[k + 1] - route[k]
    return float(np.arctan2(d[1], d[0]))
