"""Inverse kinematics: MediaPipe's 33 3D pose landmarks -> SMPL global orientation and 23
body-joint rotations (relative to a template's rest pose).

- Global orientation: the torso frame (x = right hip -> left hip, y = hips -> shoulders,
  orthogonalised, z = x cross y) of the landmarks, relative to the same frame of the
  template's rest joints.
- Limbs (hips, knees, ankles, shoulders, elbows): each joint gets the smallest rotation
  that turns its rest bone (already moved by its parents) onto the observed bone direction
  (swing only: landmarks do not fix the twist about a bone). Spine, neck, collars, head,
  wrists and hands stay at rest.
Only directions are used, so the person's bone lengths need not match the template's.
"""
from __future__ import annotations

import numpy as np

from omnire_body.rest import align_directions

# MediaPipe pose landmark indices (person's left/right).
MP = {"l_shoulder": 11, "r_shoulder": 12, "l_elbow": 13, "r_elbow": 14, "l_wrist": 15, "r_wrist": 16,
      "l_hip": 23, "r_hip": 24, "l_knee": 25, "r_knee": 26, "l_ankle": 27, "r_ankle": 28,
      "l_foot": 31, "r_foot": 32}
# SMPL joint -> landmark it sits at.
SMPL_FROM_MP = {1: "l_hip", 2: "r_hip", 4: "l_knee", 5: "r_knee", 7: "l_ankle", 8: "r_ankle", 10: "l_foot",
                11: "r_foot", 16: "l_shoulder", 17: "r_shoulder", 18: "l_elbow", 19: "r_elbow", 20: "l_wrist",
                21: "r_wrist"}
# (joint, child) bones solved in kinematic order.
LIMBS = ((1, 4), (4, 7), (7, 10), (2, 5), (5, 8), (8, 11), (16, 18), (18, 20), (17, 19), (19, 21))


def _torso_frame(l_hip, r_hip, l_sh, r_sh) -> np.ndarray:
    x = l_hip - r_hip
    x = x / np.linalg.norm(x)
    up = (l_sh + r_sh) / 2 - (l_hip + r_hip) / 2
    y = up - (up @ x) * x
    y = y / np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def landmarks_to_smpl(landmarks: np.ndarray, joints: np.ndarray, parents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve a body pose from landmarks.

    Args:
        landmarks: (33, 3) MediaPipe world landmarks (metres, any rigid frame: the returned
            orientation is expressed in it; MediaPipe's is camera-aligned, x right, y down).
        joints: (24, 3) rest joints of the body template (SMPL canonical frame).
        parents: (24,) SMPL parents.
    Returns:
        global_orient (3, 3) body-to-landmark-frame, body_pose (23, 3, 3).
    """
    P = {j: landmarks[MP[name]] for j, name in SMPL_FROM_MP.items()}
    G = _torso_frame(P[1], P[2], P[16], P[17]) @ _torso_frame(joints[1], joints[2], joints[16], joints[17]).T
    W = [None] * 24  # world rotation of each joint
    W[0] = G
    local = np.tile(np.eye(3), (24, 1, 1))
    solved = dict(LIMBS)
    for j in range(1, 24):
        parent_W = W[parents[j]]
        if j in solved:
            c = solved[j]
            Q = align_directions(parent_W @ (joints[c] - joints[j]), P[c] - P[j])
            local[j] = parent_W.T @ Q @ parent_W
        W[j] = parent_W @ local[j]
    return G, local[1:]
