"""Human pose pipeline: IoU matching of per-camera tracklets to 3D tracks, SLERP completion,
world-frame orientation, estimator plumbing."""
import numpy as np

from omnire.geometry import axis_angle_to_rotmat
from omnire_body.humanpose import (
    HumanTracklet,
    complete_rotations,
    match_tracklets,
    prepare_human_poses,
    project_box,
    sequences_from_tracklets,
)

from scene_helpers import make_tiny_scene


def rot_z(a):
    return axis_angle_to_rotmat(np.array([0.0, 0.0, a]))


def scene_with_people(tmp_path, ys=(-1.6, 0.0, 1.6)):
    from omnire.data.scene import ActorTrack

    scene = make_tiny_scene(tmp_path, frames=8, width=96, height=64)
    F = scene.num_frames
    for k, y in enumerate(ys):
        poses = np.tile(np.eye(4), (F, 1, 1))
        poses[:, 0, 3] = 5.0 + 0.4 * np.arange(F)
        poses[:, 1, 3] = y
        poses[:, 2, 3] = -0.6
        scene.tracks.append(ActorTrack(f"p{k}", "Pedestrian", "human", poses, np.array([0.6, 0.6, 1.75]),
                                       np.ones(F, bool)))
    return scene


def tracklet_for(scene, track, camera, frames, rng, go_world=None, bp=None):
    boxes = np.stack([project_box(track, scene, camera, int(f)) for f in frames]) + rng.normal(0, 0.7, (len(frames), 4))
    F = len(frames)
    c2w = scene.cameras[camera].cam_to_world
    go_world = np.tile(np.eye(3), (scene.num_frames, 1, 1)) if go_world is None else go_world
    go_cam = np.stack([c2w[f][:3, :3].T @ go_world[f] for f in frames])
    bp = np.tile(np.eye(3), (F, 23, 1, 1)) if bp is None else bp[frames]
    return HumanTracklet(camera, np.asarray(frames), boxes, go_cam, bp, np.zeros((F, 10)), "fake")


def test_iou_matching_recovers_assignment_with_dropped_and_swapped_detections(tmp_path):
    scene = scene_with_people(tmp_path)
    rng = np.random.default_rng(0)
    humans = [t for t in scene.tracks if t.category == "human"]
    tracklets, truth = [], {}
    for cam in range(2):
        for k in rng.permutation(3):  # tracklet order unrelated to track order
            frames = np.sort(rng.choice(8, 5, replace=False))  # dropped detections
            truth[len(tracklets)] = humans[k].track_id
            tracklets.append(tracklet_for(scene, humans[k], cam, frames, rng))
    # Identity switch: in one frame the first tracklet holds its neighbour's box.
    t0 = tracklets[0]
    k0 = int(truth[0][1:])
    other = humans[(k0 + 1) % 3]
    t0.boxes[1] = project_box(other, scene, t0.camera, int(t0.frames[1]))
    # A false positive far from every pedestrian (sky) matches nothing.
    tracklets.append(HumanTracklet(0, np.arange(3), np.tile([40.0, 0.0, 44.0, 3.0], (3, 1)),
                                   np.tile(np.eye(3), (3, 1, 1)), np.tile(np.eye(3), (3, 23, 1, 1))))
    assignment = match_tracklets(scene, tracklets)
    assert assignment == truth
    # The switched frame is not taken as an observation of that person.
    seqs = sequences_from_tracklets(scene, [t0], {0: truth[0]})
    assert not seqs[truth[0]].valid[int(t0.frames[1])]


def test_completion_interpolates_gaps_and_keeps_observations():
    F = 9
    angles = np.linspace(0, 1.6, F)
    rots = np.stack([rot_z(a) for a in angles])[:, None].repeat(2, axis=1)  # (F, 2, 3, 3)
    valid = np.zeros(F, bool)
    valid[[1, 2, 6]] = True
    garbage = rots.copy()
    garbage[~valid] = np.diag([1.0, -1.0, -1.0])  # whatever sits in the gaps is ignored
    out = complete_rotations(garbage, valid)
    np.testing.assert_array_equal(out[valid], garbage[valid])  # observed frames untouched
    for f in (3, 4, 5):  # between frames 2 and 6: SLERP = linear in the angle about z
        np.testing.assert_allclose(out[f], rots[f], atol=1e-9)
    np.testing.assert_allclose(out[0], rots[1], atol=1e-12)  # before the first: hold
    np.testing.assert_allclose(out[8], rots[6], atol=1e-12)  # after the last: hold
    assert np.allclose(complete_rotations(rots, np.zeros(F, bool)), np.eye(3))


def test_world_orientation_and_completion_from_tracklets(tmp_path):
    scene = scene_with_people(tmp_path, ys=(0.5,))
    track = scene.tracks[-1]
    rng = np.random.default_rng(1)
    go_world = np.stack([rot_z(0.1 * f) @ axis_angle_to_rotmat(np.array([0.0, 0.3, 0.0])) for f in range(8)])
    bp = axis_angle_to_rotmat(rng.normal(0, 0.3, (8, 23, 3)))
    t_a = tracklet_for(scene, track, 0, np.array([0, 1, 2, 6, 7]), rng, go_world, bp)
    t_b = tracklet_for(scene, track, 1, np.array([2, 3]), rng, go_world, bp)
    seqs = sequences_from_tracklets(scene, [t_a, t_b], {0: track.track_id, 1: track.track_id})
    seq = seqs[track.track_id]
    obs = [0, 1, 2, 3, 6, 7]
    assert seq.valid.tolist() == [f in obs for f in range(8)]
    np.testing.assert_allclose(seq.global_orient[obs], go_world[obs], atol=1e-9)  # camera -> world
    np.testing.assert_allclose(seq.body_pose[obs], bp[obs], atol=1e-12)
    assert seq.betas.shape == (10,) and seq.source == "fake"


class FakeEstimator:
    """Stands in for a pose-estimator plugin: one tracklet per region hint."""

    name = "fake"

    def __init__(self):
        self.calls = 0

    def estimate(self, scene, camera, rois):
        self.calls += 1
        per_key = {}
        for f, items in rois.items():
            for key, box in items:
                per_key.setdefault(key, []).append((f, box))
        out = []
        for key, obs in per_key.items():
            frames = np.array([f for f, _ in obs])
            n = len(frames)
            out.append(HumanTracklet(camera, frames, np.stack([b for _, b in obs]), np.tile(np.eye(3), (n, 1, 1)),
                                     np.tile(np.eye(3), (n, 23, 1, 1)), np.zeros((n, 0)), "fake", key))
        return out


def test_prepare_human_poses_paths(tmp_path):
    scene = scene_with_people(tmp_path)
    scene.tracks[-1].present[:] = False
    scene.tracks[-1].present[0] = True
    scene.tracks[-1].poses[0, 0, 3] = -20.0  # only ever behind the cameras: the estimator cannot see it
    est = FakeEstimator()
    paths = prepare_human_poses(scene, estimator=est, min_box_height=5)
    assert est.calls == 2
    assert paths["p0"].startswith("fake: 8 observed") and paths["p1"].startswith("fake:")
    assert paths["p2"].startswith("neutral")
    assert prepare_human_poses(scene, estimator=est, min_box_height=5) == paths and est.calls == 2  # idempotent


def test_partly_hidden_person_matches_by_the_rows_it_is_seen_in(tmp_path):
    """A tracklet that saw only the head and shoulders of p1 (its box: the top fifth of the
    projected box, IoU 0.2 with it) is matched to p1 and its frames kept as keypoint
    observations; the same boxes moved onto the neighbour p0 match p0, not p1."""
    from omnire_body.humanpose import box_iou, keypoint_observations

    scene = scene_with_people(tmp_path)
    p0, p1 = scene.tracks[-3], scene.tracks[-2]
    frames = np.arange(8)

    def head_and_shoulders(track):
        boxes = np.stack([project_box(track, scene, 0, int(f)) for f in frames])
        boxes[:, 3] = boxes[:, 1] + 0.18 * (boxes[:, 3] - boxes[:, 1])
        kp = np.zeros((8, 24, 3))
        kp[..., 2] = 0.9
        return HumanTracklet(0, frames, boxes, np.tile(np.eye(3), (8, 1, 1)), np.tile(np.eye(3), (8, 23, 1, 1)),
                             keypoints=kp)

    seen = head_and_shoulders(p1)
    assert max(box_iou(b, project_box(p1, scene, 0, int(f))) for b, f in zip(seen.boxes, frames)) < 0.2
    humans = [t for t in scene.tracks if t.category == "human"]
    assert match_tracklets(scene, [seen], humans) == {0: "p1"}
    assert len(keypoint_observations(scene, p1, [seen])) == 8
    assert match_tracklets(scene, [head_and_shoulders(p0)], humans) == {0: "p0"}


def test_occluder_outlines():
    """A walker's body outline lies inside its projected box and is narrower; a car's is
    lower; with extent 1 the outline's extent is the projected box."""
    from omnire.data.scene import ActorTrack
    from omnire_body.humanpose import OCCLUDER_EXTENT, convex_hull, project_outline

    assert convex_hull(np.array([[0, 0], [2, 0], [1, 1], [2, 2], [0, 2], [1, 0.5]])).tolist() == \
        [[0, 0], [2, 0], [2, 2], [0, 2]]
    from omnire.data.scene import CameraSequence, SceneData

    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cam = CameraSequence("front", 640, 480, K, c2w[None], [None], np.zeros(1))
    pose = np.eye(4)
    pose[:3, :3] = rot_z(np.pi / 2)
    pose[:3, 3] = [6.0, 0.5, -0.5]
    walker = ActorTrack("w", "Pedestrian", "human", pose[None], np.array([1.02, 0.57, 1.69]), np.ones(1, bool))
    car = ActorTrack("c", "Car", "vehicle", pose[None], np.array([4.5, 1.8, 1.5]), np.ones(1, bool))
    scene = SceneData("s", [cam], np.zeros(1), np.zeros(1, int), np.zeros(1, int), np.zeros(0, int), None, [walker, car])
    for track in (walker, car):
        box = project_box(track, scene, 0, 0)
        full = project_outline(track, scene, 0, 0)
        np.testing.assert_allclose([*full.min(0), *full.max(0)], box, atol=1e-9)
        body = project_outline(track, scene, 0, 0, OCCLUDER_EXTENT[track.category])
        assert (body.min(0) >= box[:2] - 1e-9).all() and (body.max(0) <= box[2:] + 1e-9).all()
        if track is walker:
            assert np.ptp(body[:, 0]) < 0.6 * (box[2] - box[0])
            assert np.ptp(body[:, 1]) > 0.95 * (box[3] - box[1])  # full height (nearer corners: a bit more)
        else:
            assert body[:, 1].min() > box[1] + 0.3 * (box[3] - box[1])  # the bonnet and boot are lower
