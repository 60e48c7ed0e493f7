"""Which actors get a node: those training observes (a camera sees them, or, with LiDAR
learned as a sensor, the LiDAR does); the others stay in the background."""
from __future__ import annotations

import numpy as np

from lidar_scene import make_lidar_scene
from omnire.api import NodeTypeSpec, observed_in_training, seen_by_lidar, visible_in_cameras
from omnire.data.scene import ActorTrack
from omnire.model import assign_tracks
from omnire.pointcloud import points_in_box


def _track(name: str, centre, size=(2.0, 2.0, 2.0), frames: int = 6) -> ActorTrack:
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, 3] = centre
    return ActorTrack(name, "Car", "vehicle", poses, np.asarray(size, dtype=float), np.ones(frames, bool))


def test_an_actor_only_the_lidar_sees_gets_a_node_when_lidar_is_learned(tmp_path):
    scene = make_lidar_scene(tmp_path)  # one camera looking along +x; a 360-degree LiDAR
    ahead = _track("ahead", (10.0, 0.0, 0.9), (2.2, 5.2, 2.0))  # the box obstacle: camera and LiDAR
    behind = _track("behind", (-8.0, 0.0, 0.5))  # behind the camera; holds ground returns
    aloft = _track("aloft", (-8.0, 0.0, 30.0))  # behind and up in the air: nothing sees it
    scene.tracks = [ahead, behind, aloft]

    # the slower obvious answer: count the returns in each box, frame by frame
    counts = {t.track_id: max(int(points_in_box(scene.lidar.points[f], t.poses[f], t.size).sum())
                              for f in scene.train_frames) for t in scene.tracks}
    assert counts["ahead"] >= 10 and counts["behind"] >= 10 and counts["aloft"] == 0
    assert visible_in_cameras(ahead, scene) and not visible_in_cameras(behind, scene)
    assert not visible_in_cameras(aloft, scene)
    assert seen_by_lidar(behind, scene) and not seen_by_lidar(aloft, scene)
    assert not seen_by_lidar(behind, scene, min_returns=counts["behind"] + 1)

    specs = {"rigid": NodeTypeSpec("rigid", "test", object, categories=frozenset({"vehicle"}), priority=10)}
    ids = lambda assigned: [t.track_id for t in assigned["rigid"]]  # noqa: E731
    assert ids(assign_tracks(scene, specs)) == ["ahead"]  # camera-only training: LiDAR-only actors stay static
    assert ids(assign_tracks(scene, specs, lidar_learning=True)) == ["ahead", "behind"]
    assert [observed_in_training(t, scene, True) for t in scene.tracks] == [True, True, False]

    scene.lidar = None  # no LiDAR: nothing but the cameras can observe
    assert not seen_by_lidar(behind, scene)
    assert ids(assign_tracks(scene, specs, lidar_learning=True)) == ["ahead"]
