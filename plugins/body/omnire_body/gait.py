"""A walking-gait prior for the body fitter: joint angles as functions of the gait phase.

The phase advances with the distance the pedestrian's box travels, one cycle (two steps)
per ``cycle`` metres, so leg phase is tied to root speed. The shape of each joint's curve
comes from clinical gait analysis (sagittal-plane angles of adults at a comfortable pace,
e.g. Perry & Burnfield, *Gait Analysis*, 2nd ed.): hip flexion/extension about 40 degrees
peak to peak, knee flexion near 10-20 degrees in stance peaking near 60 degrees in early
swing, ankle about +/-15 degrees, the arms swinging against the same-side leg by 15-30
degrees with the elbows slightly flexed. The amplitudes, the cycle length and the phase
offset are free parameters of the fit (:mod:`omnire_body.fitting`); these are only their
starting values and prior means.

Sign conventions (SMPL canonical frame: x = body's left, y up, z forward): a rotation
about +x by a positive angle swings a hanging limb backwards; knee flexion is positive.
Phase: the left hip is most flexed (thigh forward) at phase pi/2; the left leg swings
(moves forward) while cos(phase) > 0.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from omnire.api import axis_angle_to_rotmat

L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE = 1, 2, 4, 5, 7, 8
L_SHOULDER, R_SHOULDER, L_ELBOW, R_ELBOW = 16, 17, 18, 19


@dataclasses.dataclass(frozen=True)
class GaitShape:
    """Prior means of the gait parameters (radians unless stated)."""

    hip: float = 0.35
    """Hip flexion/extension amplitude (about 40 degrees peak to peak)."""
    knee_stance: float = 0.12
    """Knee flexion kept through stance."""
    knee_swing: float = 0.85
    """Extra knee flexion at its early-swing peak (total about 55-60 degrees)."""
    ankle: float = 0.15
    """Ankle plantar/dorsiflexion amplitude."""
    arm: float = 0.25
    """Shoulder flexion/extension amplitude (arm swing)."""
    elbow: float = 0.35
    """Elbow flexion (forearm forward)."""
    cycle_per_height: float = 0.8
    """Distance per gait cycle over body height (step length about 0.4 of the height)."""
    walking_speed: float = 0.6
    """Root speed (m/s) at which the stride reaches its full amplitude; slower walkers
    fade towards a standing pose (amplitude proportional to speed below it)."""
    standing_speed: float = 0.15
    """Below this root speed (m/s) the stride amplitude is zero."""


def stride_weight(speed: np.ndarray, shape: GaitShape = GaitShape()) -> np.ndarray:
    """(F,) in [0, 1]: how much of a full stride a walker at ``speed`` (F,) m/s takes."""
    span = max(shape.walking_speed - shape.standing_speed, 1e-6)
    return np.clip((np.asarray(speed, dtype=np.float64) - shape.standing_speed) / span, 0.0, 1.0)


def gait_rotations(phase: torch.Tensor, weight: torch.Tensor, amps: torch.Tensor,
                   neutral: torch.Tensor) -> torch.Tensor:
    """Body pose of the gait prior.

    Args:
        phase: (F,) gait phase (radians).
        weight: (F,) stride weight in [0, 1] (:func:`stride_weight`).
        amps: (6,) hip, knee_stance, knee_swing, ankle, arm, elbow (see :class:`GaitShape`).
        neutral: (23, 3, 3) standing pose the gait is built on (arms hanging; from
            :func:`omnire_body.rest.neutral_body_pose`).
    Returns:
        (F, 23, 3, 3) joint rotations relative to the parents (SMPL order, no pelvis).
    """
    F = phase.shape[0]
    hip, k0, k1, ankle, arm, elbow = amps.unbind(0)
    s, c = torch.sin(phase) * weight, torch.cos(phase)
    aa = torch.zeros(F, 24, 3, dtype=phase.dtype)
    aa[:, L_HIP, 0] = -hip * s
    aa[:, R_HIP, 0] = hip * s
    aa[:, L_KNEE, 0] = k0 + k1 * weight * torch.clamp(c, min=0) ** 2
    aa[:, R_KNEE, 0] = k0 + k1 * weight * torch.clamp(-c, min=0) ** 2
    aa[:, L_ANKLE, 0] = -ankle * s
    aa[:, R_ANKLE, 0] = ankle * s
    local = axis_angle_to_rotmat(aa)  # (F, 24, 3, 3)
    base = neutral.to(phase.dtype).expand(F, 23, 3, 3)
    # Arms: the hanging arm of the neutral pose swung about the body's x axis; the elbow
    # bends the forearm forward about the same world axis (conjugated into the upper arm's frame).
    swing = torch.stack([arm * s, -arm * s], 1)  # (F, 2): left, right
    R_sw = axis_angle_to_rotmat(torch.stack([swing, torch.zeros_like(swing), torch.zeros_like(swing)], -1))
    shoulders = R_sw @ base[:, [L_SHOULDER - 1, R_SHOULDER - 1]]  # (F, 2, 3, 3)
    bend = axis_angle_to_rotmat(torch.stack([-elbow.expand(F, 2), torch.zeros(F, 2, dtype=phase.dtype),
                                             torch.zeros(F, 2, dtype=phase.dtype)], -1))
    elbows = shoulders.transpose(-1, -2) @ bend @ shoulders
    out = base.clone()
    legs = [L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE]
    out[:, [j - 1 for j in legs]] = local[:, legs] @ base[:, [j - 1 for j in legs]]
    out[:, [L_SHOULDER - 1, R_SHOULDER - 1]] = shoulders
    out[:, [L_ELBOW - 1, R_ELBOW - 1]] = elbows @ base[:, [L_ELBOW - 1, R_ELBOW - 1]]
    return out


def default_amplitudes(shape: GaitShape = GaitShape()) -> np.ndarray:
    """(6,) prior means in the order :func:`gait_rotations` takes."""
    return np.array([shape.hip, shape.knee_stance, shape.knee_swing, shape.ankle, shape.arm, shape.elbow])
