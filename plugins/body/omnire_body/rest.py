"""An upright body standing in its box: the frame change from SMPL's canonical body frame
to the actor box, and the neutral standing pose.

Used by the pose pipeline (:mod:`omnire_body.humanpose`), the body fitter
(:mod:`omnire_body.fitting`), the SMPL node type, the simulation plugin and the synthetic
generator's walkers, so that every one of them places a body the same way.
"""
from __future__ import annotations

import numpy as np

BODY_TO_BOX = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""SMPL canonical axes (x = body's left, y up, z forward) -> box axes (x heading, y left,
z up): the orientation, relative to its box, of an upright body facing along the box's
heading (body front +z -> +x, body left +x -> +y, body up +y -> +z)."""


def align_directions(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking direction ``a`` (3,) to direction ``b`` (3,)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:  # opposite: turn by pi about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)


def neutral_body_pose(joints: np.ndarray, arm_abduction_deg: float = 8.0) -> np.ndarray:
    """(23, 3, 3) standing pose for a template with rest joints ``joints`` (24, 3): every
    joint at rest except the shoulders, which hang the upper arms down beside the body
    (works for T-pose SMPL and A-pose templates alike)."""
    bp = np.tile(np.eye(3), (23, 1, 1))
    a = np.deg2rad(arm_abduction_deg)
    for shoulder, elbow, side in ((16, 18, 1.0), (17, 19, -1.0)):  # x = body's left
        bp[shoulder - 1] = align_directions(joints[elbow] - joints[shoulder], np.array([side * np.sin(a), -np.cos(a), 0.0]))
    return bp
