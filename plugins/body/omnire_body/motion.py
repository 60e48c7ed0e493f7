"""Procedural body motion on the SMPL skeleton: a walking gait cycle.

Shared by the synthetic scene generator (its walkers) and the simulation plugin (walking
motions for pedestrians given new paths). Rotations are in SMPL joint order, in SMPL's
canonical body frame (x = the body's left, y up, z forward).
"""
from __future__ import annotations

import numpy as np

from omnire.api import axis_angle_to_rotmat

GAIT_CYCLE_METRES = 1.3
"""Distance walked per gait cycle (two steps) by an adult at an ordinary pace."""


def gait_pose(phase: np.ndarray, amplitude: "np.ndarray | float" = 1.0) -> np.ndarray:
    """Walking body pose (F, 23, 3, 3) from a gait phase (F,) in radians, SMPL joint order.

    ``amplitude`` (scalar or (F,)) scales the swing of legs, arms and torso: 1 is a full
    walking stride, 0 a standing pose (arms lowered, knees and elbows slightly bent), so a
    walker slowing to a stop can fade its stride out.

    In SMPL's canonical frame (x left, y up, z forward) a rotation about +x by a positive
    angle swings a downward limb backwards.
    """
    phase = np.asarray(phase, dtype=np.float64)
    F = len(phase)
    amp = np.broadcast_to(np.asarray(amplitude, dtype=np.float64), (F,))
    aa = np.zeros((F, 24, 3))
    s = amp * np.sin(phase)
    aa[:, 1, 0] = -0.45 * s  # left hip forward when s > 0
    aa[:, 2, 0] = 0.45 * s
    aa[:, 4, 0] = 0.08 + 0.65 * (amp * np.clip(np.cos(phase), 0, None) ** 1.5)  # left knee bends in swing
    aa[:, 5, 0] = 0.08 + 0.65 * (amp * np.clip(-np.cos(phase), 0, None) ** 1.5)
    aa[:, 7, 0] = -0.15 * s  # ankles follow a little
    aa[:, 8, 0] = 0.15 * s
    aa[:, 16, 0] = 0.35 * s  # arms swing against the legs
    aa[:, 17, 0] = -0.35 * s
    aa[:, 16, 2] = -0.75  # lower the A-pose arms towards the body
    aa[:, 17, 2] = 0.75
    aa[:, 18, 0] = -0.3 - 0.2 * np.clip(-s, 0, None)  # elbows flex forward
    aa[:, 19, 0] = -0.3 - 0.2 * np.clip(s, 0, None)
    aa[:, 3, 1] = 0.08 * s  # a little torso twist
    aa[:, 9, 1] = -0.05 * s
    R = axis_angle_to_rotmat(aa)  # (F, 24, 3, 3)
    return R[:, 1:]


def gait_phase(distance: np.ndarray, cycle: float = GAIT_CYCLE_METRES, phase0: float = 0.0) -> np.ndarray:
    """Gait phase (radians) after walking ``distance`` metres (any shape): one cycle per
    ``cycle`` metres, so the feet keep pace with the ground at any speed."""
    if not cycle > 0:
        raise ValueError(f"gait cycle {cycle}: must be > 0 metres")
    return phase0 + 2.0 * np.pi * np.asarray(distance, dtype=np.float64) / cycle
