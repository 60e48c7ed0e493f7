"""Body fitter: gait-prior signs, poses recovered from LiDAR points and from 2D keypoints
(better than the neutral fallback, against a walking gait unlike the prior's means), the
fused pipeline path and its log line, and the benchmark's error metrics."""
import numpy as np
import pytest
import torch

from omnire.data.scene import ActorTrack
from omnire.geometry import axis_angle_to_rotmat, rot_z
from omnire_body import forward_kinematics, lbs, load_template
from omnire_body.bench import aggregate, joint_errors, procrustes
from omnire_body.fitting import BodyFitter, FitConfig, KeypointObservation, TrackData
from omnire_body.gait import default_amplitudes, gait_rotations
from omnire_body.humanpose import FusedPoseSequence, describe_sequence, prepare_human_poses
from omnire_body.rest import BODY_TO_BOX, neutral_body_pose

from scene_helpers import make_tiny_scene

F = 12


@pytest.fixture(scope="module")
def template():
    return load_template()


def true_walk(template, F=F, speed=1.3, yaw=0.4, seed=0):
    """A walker unlike the prior's means: hip swing 0.5 rad, knee 0.6, arms 0.4, phase 1.0
    rad, 1.25 m per cycle, plus random joint noise. Returns box poses (F, 4, 4), world
    global_orient (F, 3, 3), body_pose (F, 23, 3, 3), centres (F, 3)."""
    rng = np.random.default_rng(seed)
    t = np.arange(F) * 0.1
    heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    centres = np.array([5.0, -1.0, 0.0]) + speed * t[:, None] * heading
    poses = np.tile(np.eye(4), (F, 1, 1))
    poses[:, :3, :3] = rot_z(np.full(F, yaw))
    poses[:, :3, 3] = centres
    phase = 1.0 + 2 * np.pi * speed * t / 1.25
    amps = torch.tensor([0.5, 0.1, 0.6, 0.1, 0.4, 0.3])
    bp = gait_rotations(torch.as_tensor(phase), torch.ones(F, dtype=torch.float64), amps.double(),
                        torch.as_tensor(neutral_body_pose(template.joints))).numpy()
    bp = bp @ axis_angle_to_rotmat(rng.normal(0, 0.05, (F, 23, 3)))
    go = poses[:, :3, :3] @ BODY_TO_BOX
    return poses, go, bp, centres


def world_vertices(template, go, bp, centres):
    """Posed vertices (F, V, 3): the template's vertical centre at ``centres``."""
    lo, hi = template.vertices[:, 1].min(), template.vertices[:, 1].max()
    c = np.array([0.0, (lo + hi) / 2, 0.0])
    out = lbs(template, go, bp).vertices  # about J0
    J0 = template.joints[0]
    c_posed = J0 + np.einsum("fij,j->fi", go, c - J0)
    return out - c_posed[:, None] + centres[:, None]


def scan(template, verts, sensor, n=80, rng=None):
    """Visible-side samples of each frame's body from ``sensor`` (vertices whose normal faces
    it), with 1 cm noise."""
    rng = rng or np.random.default_rng(1)
    out = []
    for v in verts:
        tri = v[template.faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        vn = np.zeros_like(v)
        np.add.at(vn, template.faces.reshape(-1), np.repeat(fn, 3, axis=0))
        facing = np.einsum("vi,vi->v", vn, sensor - v) > 0
        idx = rng.choice(np.flatnonzero(facing), n, replace=False)
        out.append(v[idx] + rng.normal(0, 0.01, (n, 3)))
    return out


def mpjpe(template, go, bp, go_t, bp_t):
    return joint_errors(template, go, bp, go_t, bp_t)[0].mean()


def test_gait_prior_signs(template):
    """Phase pi/2: left thigh forward (knee in front of the hip along the body's +z), the
    right arm forward; swinging leg's knee flexed, stance knee nearly straight."""
    bp = gait_rotations(torch.tensor([np.pi / 2, 0.0]), torch.ones(2), torch.as_tensor(default_amplitudes()).float(),
                        torch.as_tensor(neutral_body_pose(template.joints)).float()).double().numpy()
    J, _ = forward_kinematics(template.joints, template.parents, np.tile(np.eye(3), (2, 1, 1)), bp)
    assert J[0, 4, 2] - J[0, 1, 2] > 0.1 and J[0, 5, 2] - J[0, 2, 2] < -0.08
    assert J[0, 21, 2] > J[0, 20, 2] + 0.1  # right wrist ahead of the left
    knee = lambda f, hip, knee_, ankle: np.degrees(np.arccos(np.dot(  # noqa: E731
        (J[f, knee_] - J[f, hip]) / np.linalg.norm(J[f, knee_] - J[f, hip]),
        (J[f, ankle] - J[f, knee_]) / np.linalg.norm(J[f, ankle] - J[f, knee_]))))
    assert knee(1, 1, 4, 7) > 40 and knee(1, 2, 5, 8) < 25  # phase 0: left leg in early swing


def test_fitter_recovers_walk_from_lidar(template):
    poses, go, bp, centres = true_walk(template)
    verts = world_vertices(template, go, bp, centres)
    points = scan(template, verts, sensor=np.array([0.0, 3.0, 0.9]))
    data = TrackData(poses, np.array([0.8, 0.6, 1.63]), np.ones(F, bool), points, [])
    fitter = BodyFitter.from_template(template, FitConfig(iterations=60))
    res = fitter.fit(data, np.arange(F) * 0.1)
    neutral = np.tile(neutral_body_pose(template.joints), (F, 1, 1, 1))
    e_fit, e_neutral = mpjpe(template, res.global_orient, res.body_pose, go, bp), mpjpe(template, go, neutral, go, bp)
    assert e_fit < 0.05 and e_fit < 0.6 * e_neutral, (e_fit, e_neutral)
    assert res.lidar_frames.all() and (res.confidence > 0.5).all()
    np.testing.assert_allclose(res.centre, centres, atol=0.06)


def test_fitter_uses_keypoints_from_two_cameras(template):
    poses, go, bp, centres = true_walk(template, yaw=-0.3, seed=2)
    J = np.stack([forward_kinematics(template.joints, template.parents, g, b)[0] for g, b in zip(go, bp)])
    J0 = template.joints[0]
    lo, hi = template.vertices[:, 1].min(), template.vertices[:, 1].max()
    c_posed = J0 + np.einsum("fij,j->fi", go, np.array([0.0, (lo + hi) / 2, 0.0]) - J0)
    J = J - c_posed[:, None] + centres[:, None]
    K = np.array([[800.0, 0, 480], [0, 800.0, 270], [0, 0, 1]])
    rng = np.random.default_rng(3)
    obs = []
    for cam_pos, look in (([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]), ([5.0, -6.0, 0.0], [0.2, 1.0, 0.0])):
        f_ = np.array(look) / np.linalg.norm(look)
        r = np.cross(f_, [0, 0, 1.0])
        r /= np.linalg.norm(r)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([r, np.cross(f_, r), f_], 1)
        c2w[:3, 3] = cam_pos
        w2c = np.linalg.inv(c2w)
        for f in range(F):
            p = J[f] @ w2c[:3, :3].T + w2c[:3, 3]
            uv = p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2]
            h = 1.63 * 800 / p[0, 2]
            conf = np.zeros(24)
            conf[[1, 2, 4, 5, 7, 8, 15, 16, 17, 18, 19, 20, 21]] = 0.9
            obs.append(KeypointObservation(f, 0, K, w2c, uv + rng.normal(0, 0.01 * h, uv.shape), conf, h, "kp"))
    data = TrackData(poses, np.array([0.8, 0.6, 1.63]), np.ones(F, bool), [None] * F, obs)
    res = BodyFitter.from_template(template, FitConfig(iterations=60)).fit(data, np.arange(F) * 0.1)
    neutral = np.tile(neutral_body_pose(template.joints), (F, 1, 1, 1))
    e_fit, e_neutral = mpjpe(template, res.global_orient, res.body_pose, go, bp), mpjpe(template, go, neutral, go, bp)
    assert e_fit < 0.06 and e_fit < 0.7 * e_neutral, (e_fit, e_neutral)
    assert res.keypoint_frames.all() and not res.lidar_frames.any()


def test_pipeline_fuses_lidar_into_a_sequence_with_confidence(tmp_path, template):
    scene = make_tiny_scene(tmp_path, frames=F, with_track=False)
    poses, go, bp, centres = true_walk(template, yaw=np.pi / 2, speed=1.0)
    poses[:, 2, 3] = centres[:, 2] = -1.5 + 0.815  # standing on the tiny scene's ground
    verts = world_vertices(template, go, bp, centres)
    body = scan(template, verts, sensor=np.array([0.0, 0.0, 0.0]), n=60)
    for f in range(F):
        if scene.lidar.points[f] is not None and f != 5:  # frame 5: no points on the body
            scene.lidar.points[f] = np.concatenate([scene.lidar.points[f], body[f]]).astype(np.float32)
    present = np.ones(F, bool)
    scene.tracks.append(ActorTrack("walker", "Pedestrian", "human", poses, np.array([0.8, 0.6, 1.63]), present))
    far = poses.copy()
    far[:, 1, 3] += 30.0  # nothing observes this one
    scene.tracks.append(ActorTrack("far", "Pedestrian", "human", far, np.array([0.8, 0.6, 1.63]), present))
    paths = prepare_human_poses(scene, fit_config=FitConfig(iterations=40))
    seq = scene.human_poses["walker"]
    assert isinstance(seq, FusedPoseSequence) and seq.source == "fit(lidar)"
    gap = next(i for i, p in enumerate(scene.lidar.points) if p is None)
    assert not seq.valid[gap] and not seq.valid[5] and seq.valid.sum() == F - 2
    assert seq.confidence[5] == 0 and (seq.confidence[seq.valid] > 0.5).all()
    assert paths["walker"].startswith(f"fit(lidar): {F - 2} of {F} frames observed (lidar {F - 2} frames")
    assert paths["far"].startswith("neutral")
    assert mpjpe(template, seq.global_orient, seq.body_pose, go, bp) < 0.06
    assert describe_sequence(seq, present) == paths["walker"]


def test_bench_metrics(template):
    rng = np.random.default_rng(0)
    a = rng.normal(size=(24, 3))
    R = axis_angle_to_rotmat(np.array([0.3, -0.2, 0.5]))
    np.testing.assert_allclose(procrustes(1.3 * a @ R.T + 2.0, a), a, atol=1e-9)
    go = axis_angle_to_rotmat(rng.normal(0, 1, (3, 3)))
    bp = axis_angle_to_rotmat(rng.normal(0, 0.3, (3, 23, 3)))
    e, pa = joint_errors(template, go, bp, go, bp)
    assert np.allclose(e, 0, atol=1e-9) and np.allclose(pa, 0, atol=1e-6)
    bp2 = bp.copy()
    bp2[:, 3] = bp[:, 3] @ axis_angle_to_rotmat(np.array([0.8, 0.0, 0.0]))  # left knee bent: its chain moves
    assert (joint_errors(template, go, bp2, go, bp)[0] > 0.005).all()
    rows = [("a", 0, 0.05, 0.04, True, 90.0, 3), ("a", 1, 0.10, 0.08, False, 30.0, 60), ("b", 0, 0.2, 0.1, True, 10, 0)]
    m = aggregate(rows)
    assert m["all"]["frames"] == 3 and m["acceptance_subset"]["frames"] == 2
    assert m["acceptance_subset"]["mpjpe_cm"] == pytest.approx(7.5) and m["all"]["posed_fraction"] == pytest.approx(2 / 3)
    assert m["by_height_px"]["80-inf"]["frames"] == 1 and m["by_lidar_points"]["50-inf"]["frames"] == 1


def test_keypoint_weight_per_estimator(template):
    """MediaPipe's keypoints are down-weighted against the LiDAR points (FitConfig
    source_keypoint_weights): keypoints with left and right swapped (a typical image
    estimator error) from the side camera pull a fit at full weight away from what 20
    LiDAR points per frame say, much less at MediaPipe's weight."""
    poses, go, bp, centres = true_walk(template, yaw=0.0, seed=4)
    verts = world_vertices(template, go, bp, centres)
    points = scan(template, verts, sensor=np.array([5.5, -6.0, 0.9]), n=20)
    J = np.stack([forward_kinematics(template.joints, template.parents, g, b)[0] for g, b in zip(go, bp)])
    lo, hi = template.vertices[:, 1].min(), template.vertices[:, 1].max()
    J0 = template.joints[0]
    J = J - (J0 + np.einsum("fij,j->fi", go, np.array([0.0, (lo + hi) / 2, 0.0]) - J0))[:, None] + centres[:, None]
    swap = np.arange(24)
    for a, b in ((1, 2), (4, 5), (7, 8), (10, 11), (13, 14), (16, 17), (18, 19), (20, 21), (22, 23)):
        swap[[a, b]] = [b, a]
    K = np.array([[800.0, 0, 480], [0, 800.0, 270], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]], 1)  # looking along +y at the walker
    c2w[:3, 3] = [5.5, -6.0, 0.0]
    w2c = np.linalg.inv(c2w)
    conf = np.full(24, 0.9)
    obs = []
    for f in range(F):
        p = J[f] @ w2c[:3, :3].T + w2c[:3, 3]
        uv = p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2]
        obs.append(KeypointObservation(f, 0, K, w2c, uv[swap], conf, 1.63 * 800 / p[0, 2], "mediapipe"))
    data = TrackData(poses, np.array([0.8, 0.6, 1.63]), np.ones(F, bool), points, obs)
    errors = {}
    for name, weights in (("lidar only", None), ("mediapipe weight", {"mediapipe": 0.1}), ("full weight", {})):
        d = data if weights is not None else TrackData(data.poses, data.size, data.present, data.points, [])
        cfg = FitConfig(iterations=60) if weights is None else FitConfig(iterations=60, source_keypoint_weights=weights)
        res = BodyFitter.from_template(template, cfg).fit(d, np.arange(F) * 0.1)
        errors[name] = mpjpe(template, res.global_orient, res.body_pose, go, bp)
    assert FitConfig().source_keypoint_weights["mediapipe"] == 0.1
    assert errors["mediapipe weight"] < errors["lidar only"] + 0.01 < errors["full weight"], errors
