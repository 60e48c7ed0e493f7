"""IK from 3D landmarks to SMPL rotations reproduces the joint positions of a known pose."""
import numpy as np

from omnire.geometry import axis_angle_to_rotmat
from omnire_body import forward_kinematics, load_template
from omnire_pose_mediapipe.ik import MP, SMPL_FROM_MP, landmarks_to_smpl


def test_ik_recovers_limb_positions():
    t = load_template()
    rng = np.random.default_rng(0)
    aa = np.zeros((23, 3))
    for j in (1, 2, 4, 5, 7, 8, 16, 17, 18, 19):
        aa[j - 1] = rng.normal(0, 0.5, 3)
    go = axis_angle_to_rotmat(rng.normal(0, 1.0, 3))
    posed, _ = forward_kinematics(t.joints, t.parents, go, axis_angle_to_rotmat(aa))
    landmarks = np.zeros((33, 3))
    for j, name in SMPL_FROM_MP.items():
        landmarks[MP[name]] = posed[j] * 0.9 + 0.3  # other bone lengths and origin: only directions count
    G, bp = landmarks_to_smpl(landmarks, t.joints, t.parents)
    np.testing.assert_allclose(G, go, atol=1e-9)
    solved, _ = forward_kinematics(t.joints, t.parents, G, bp)
    # Every joint up to the wrists; the hands hang off the forearm axis, so the forearm
    # twist (which landmarks do not fix) moves them.
    np.testing.assert_allclose(solved[:22], posed[:22], atol=1e-9)


def test_registered_and_reports_availability():
    from omnire.plugins import load_plugins

    spec = load_plugins().pose_estimators.get("mediapipe")
    ok, why = spec.available()
    assert ok or "mediapipe" in why
