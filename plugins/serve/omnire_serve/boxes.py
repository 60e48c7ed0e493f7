"""Oriented boxes on the ground plane: corners and overlap (separating axis test)."""
from __future__ import annotations

import numpy as np


def footprint(centre: np.ndarray, yaw: float, length: float, width: float) -> np.ndarray:
    """(4, 2) corners of a box of ``length`` x ``width`` metres centred at ``centre`` (2,)
    and turned ``yaw`` radians, counter-clockwise from the front left."""
    c, s = np.cos(yaw), np.sin(yaw)
    fwd, left = np.array([c, s]) * length / 2, np.array([-s, c]) * width / 2
    ctr = np.asarray(centre, dtype=np.float64)[:2]
    return np.stack([ctr + fwd + left, ctr - fwd + left, ctr - fwd - left, ctr + fwd - left])


def footprint_of(pose: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(4, 2) ground footprint of a box with pose (4, 4) and size (length, width, height)."""
    yaw = float(np.arctan2(pose[1, 0], pose[0, 0]))
    return footprint(pose[:2, 3], yaw, float(size[0]), float(size[1]))


def overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """True when the convex quadrilaterals ``a`` and ``b`` (4, 2) share any point (touching
    counts): no edge normal of either separates their projections."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], 1)
        for n in normals:
            pa, pb = a @ n, b @ n
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True
