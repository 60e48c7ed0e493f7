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


def gap_ahead(ego_xy, ego_yaw: float, ego_length: float, ego_width: float, pose: np.ndarray, size: np.ndarray,
              lateral_margin: float = 0.0, horizon: float = 40.0):
    """Metres of free road between the ego's front and a box (pose (4, 4), size (3,)) in
    its path ahead: the box's footprint reaches into the ego's width (plus
    ``lateral_margin`` each side) and lies ahead of the ego's front within ``horizon``
    metres. None when the box is not in the path ahead."""
    c, s = np.cos(ego_yaw), np.sin(ego_yaw)
    rel = footprint_of(pose, size) - np.asarray(ego_xy, dtype=np.float64)[:2]
    fwd, left = rel @ [c, s], rel @ [-s, c]  # the box's corners in the ego frame
    half = ego_width / 2 + lateral_margin
    # the nearest point of the footprint within the ego's lateral band |left| <= half: a
    # corner inside the band or where an edge crosses one of its sides
    near = [f for f, lat in zip(fwd, left) if abs(lat) <= half]
    for k in range(4):
        f0, l0, f1, l1 = fwd[k], left[k], fwd[(k + 1) % 4], left[(k + 1) % 4]
        for side in (-half, half):
            if (l0 - side) * (l1 - side) < 0:
                near.append(f0 + (side - l0) / (l1 - l0) * (f1 - f0))
    if not near:
        return None
    front = min(near)
    if max(near) <= ego_length / 2 or front > horizon:
        return None
    return float(front) - ego_length / 2
