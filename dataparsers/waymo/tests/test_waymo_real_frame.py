"""The one real Waymo frame of the shared data: calibration checked against the dataset's
own 2D labels.

``Frame.projected_lidar_labels`` are, per dataset.proto, "the smallest image axis aligned
rectangle that can cover all projected points from the 3D LiDAR label", clamped to the
image, with id ``<laser label id>_<CAMERA NAME>``: projecting the 8 corners of each laser
label with our intrinsics, distortion, extrinsics and per-image poses must give the same
rectangle. ``Frame.camera_labels`` are annotated on the images independently (their ids
are not laser ids and this frame has no associations); they are checked loosely.
"""
from __future__ import annotations

import collections

import numpy as np
import pytest

from omnire.api import ConfigError
from omnire_waymo import ATTRIBUTION, WaymoConfig
from omnire_waymo.dataparser import CAMERA_NAMES
from omnire_waymo.tfrecord import TFRecordReader
from omnire_waymo.wod import dataset_pb2

pytestmark = pytest.mark.filterwarnings("ignore:.*no range images in the loaded frames")

ALL5 = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT")
EDGE_TOLERANCE_PX = 1.0
"""Every edge of our projected rectangle within 1 px of the dataset's (measured: max 0.2 px)."""
SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * 0.5


@pytest.fixture(scope="module")
def scene(real_frame, tmp_path_factory):
    return WaymoConfig(data=real_frame, cameras=ALL5, scale=1.0, image_dir=tmp_path_factory.mktemp("img")).setup().parse()


@pytest.fixture(scope="module")
def frame(real_frame):
    with TFRecordReader(real_frame) as rd:
        return dataset_pb2.Frame.FromString(next(iter(rd)))


def project_box(cam, track, f=0):
    """Rectangle (u0, v0, u1, v1) covering the 8 projected corners (OpenCV distortion),
    clamped to the image; None when a corner is behind the camera or outside the range
    where the radial distortion model is valid (Waymo's camera model rejects 1 + k1 r^2 +
    k2 r^4 + k3 r^6 outside [0.8, 1.2])."""
    size = track.extras["size_per_frame"][f]
    corners = (SIGNS * size) @ track.poses[f, :3, :3].T + track.poses[f, :3, 3]
    w2c = np.linalg.inv(cam.cam_to_world[f])
    pc = corners @ w2c[:3, :3].T + w2c[:3, 3]
    if (pc[:, 2] <= 0.1).any():
        return None
    x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    k1, k2, p1, p2, k3 = cam.distortion
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    if ((radial < 0.8) | (radial > 1.2)).any():
        return None
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    K = cam.intrinsics
    u = np.clip(K[0, 0] * xd + K[0, 2], 0, cam.width)
    v = np.clip(K[1, 1] * yd + K[1, 2], 0, cam.height)
    return np.array([u.min(), v.min(), u.max(), v.max()])


def label_rect(box):
    """2D label box (centre, length = x extent, width = y extent) -> (u0, v0, u1, v1)."""
    return np.array([box.center_x - box.length / 2, box.center_y - box.width / 2,
                     box.center_x + box.length / 2, box.center_y + box.width / 2])


def test_loads_cameras_and_labels(scene, real_frame):
    assert scene.name == "1024360143612057520_3580_000_3600_000" and scene.num_frames == 1
    assert [c.name for c in scene.cameras] == list(ALL5)
    assert [(c.width, c.height) for c in scene.cameras] == [(1920, 1280)] * 3 + [(1920, 886)] * 2
    for c in scene.cameras:
        assert c.distortion.shape == (5,) and abs(c.distortion[1]) > 0.2  # k2 ~ -0.33: a real lens
        assert c.image_paths[0].is_file() and c.image_paths[0].read_bytes()[:2] == b"\xff\xd8"
        assert not c.image_paths[0].is_relative_to(real_frame.parent)  # nothing written to the dataset
        for key in ("vehicle_pose", "pose_timestamp", "velocity", "shutter", "camera_trigger_time",
                    "camera_readout_done_time", "rolling_shutter_direction"):
            assert len(c.extras[key]) == 1
        # exposure-centre time lies between the trigger and the end of the readout
        assert c.extras["camera_trigger_time"][0] < c.timestamps[0] < c.extras["camera_readout_done_time"][0]
    assert scene.lidar is None  # this frame's lasers hold no range images
    cats = collections.Counter(t.category for t in scene.tracks)
    assert cats == {"vehicle": 37, "other": 25, "human": 12, "cyclist": 1}
    assert {t.class_name for t in scene.tracks} == {"TYPE_VEHICLE", "TYPE_SIGN", "TYPE_PEDESTRIAN", "TYPE_CYCLIST"}
    assert scene.attribution == ATTRIBUTION
    # world anchored at the vehicle: origin, heading along +x, z up
    assert np.allclose(scene.ego_poses[0][:3, 3], 0) and abs(scene.ego_poses[0][1, 0]) < 1e-12
    front = scene.cameras[0].cam_to_world[0]
    assert front[0, 2] > 0.99 and front[2, 1] < -0.99  # looks along x, image down = world down


def test_corners_reproduce_projected_lidar_labels(scene, frame):
    tracks = {t.track_id: t for t in scene.tracks}
    compared, skipped = 0, 0
    for cl in frame.projected_lidar_labels:
        cam = scene.cameras[scene.camera_index(CAMERA_NAMES[cl.name])]
        for lab in cl.labels:
            suffix = "_" + cam.name
            assert lab.id.endswith(suffix)
            rect = project_box(cam, tracks[lab.id[: -len(suffix)]])
            if rect is None:
                skipped += 1
                continue
            err = np.abs(rect - label_rect(lab.box)).max()
            assert err < EDGE_TOLERANCE_PX, (cam.name, lab.id, rect, label_rect(lab.box))
            compared += 1
    assert compared >= 55 and compared + skipped == 62


def test_a_wrong_calibration_fails_the_same_check(scene, frame):
    # The check is sharp: a 2-pixel principal point error or skipping the lens model breaks it.
    cam = scene.cameras[0]
    tracks = {t.track_id: t for t in scene.tracks}
    labels = [lab for cl in frame.projected_lidar_labels if cl.name == 1 for lab in cl.labels]
    shifted = dataclass_copy(cam, intrinsics=cam.intrinsics + np.array([[0, 0, 2.0], [0, 0, 0], [0, 0, 0]]))
    pinhole = dataclass_copy(cam, distortion=np.zeros(5))
    for variant in (shifted, pinhole):
        errs = [np.abs(r - label_rect(lab.box)).max() for lab in labels
                if (r := project_box(variant, tracks[lab.id[:-6]])) is not None]
        assert max(errs) > EDGE_TOLERANCE_PX


def dataclass_copy(obj, **changes):
    import dataclasses

    return dataclasses.replace(obj, **changes)


def test_camera_labels_agree(scene, frame):
    # Independent 2D annotations: each camera label's centre should fall inside the projected
    # box of the same-class object that overlaps it most (many camera labels are objects
    # beyond the LiDAR labels' range, so only matched ones count).
    types = {1: "TYPE_VEHICLE", 2: "TYPE_PEDESTRIAN", 4: "TYPE_CYCLIST"}
    matched = inside = 0
    for cl in frame.camera_labels:
        cam = scene.cameras[scene.camera_index(CAMERA_NAMES[cl.name])]
        rects = [(t, project_box(cam, t)) for t in scene.tracks]
        for lab in cl.labels:
            L = label_rect(lab.box)
            best, best_iou = None, 0.3
            for t, r in rects:
                if r is None or t.class_name != types.get(lab.type):
                    continue
                w = max(0.0, min(L[2], r[2]) - max(L[0], r[0]))
                h = max(0.0, min(L[3], r[3]) - max(L[1], r[1]))
                iou = w * h / ((L[2] - L[0]) * (L[3] - L[1]) + (r[2] - r[0]) * (r[3] - r[1]) - w * h)
                if iou > best_iou:
                    best, best_iou = r, iou
            if best is not None:
                matched += 1
                inside += best[0] <= lab.box.center_x <= best[2] and best[1] <= lab.box.center_y <= best[3]
    assert matched >= 20 and inside == matched


def test_scale_and_camera_selection(real_frame, tmp_path):
    s = WaymoConfig(data=real_frame, image_dir=tmp_path, scale=0.25, load_lidar=False).setup().parse()
    assert [c.name for c in s.cameras] == ["FRONT", "FRONT_LEFT", "FRONT_RIGHT"]  # default: front three
    full = WaymoConfig(data=real_frame, image_dir=tmp_path, scale=1.0, cameras=("front",), load_lidar=False).setup().parse()
    a, b = s.cameras[0], full.cameras[0]
    assert (a.width, a.height) == (480, 320)
    assert np.allclose(a.intrinsics[:2], b.intrinsics[:2] * 0.25) and np.array_equal(a.distortion, b.distortion)
    with pytest.raises(ConfigError, match="'REAR' is not calibrated.*cameras present: \\['FRONT'"):
        WaymoConfig(data=real_frame, image_dir=tmp_path, cameras=("REAR",)).setup().parse()
    with pytest.raises(ConfigError, match="'BACK' is not calibrated.*Waymo cameras"):
        WaymoConfig(data=real_frame, image_dir=tmp_path, cameras=("BACK",)).setup().parse()
    with pytest.raises(ConfigError, match="frames 1..-1 .* select nothing of the 1 frames"):
        WaymoConfig(data=real_frame, image_dir=tmp_path, start_frame=1).setup().parse()


def test_camera_time_modes(real_frame, tmp_path):
    exp = WaymoConfig(data=real_frame, image_dir=tmp_path, camera_time="exposure").setup().parse()
    pose = WaymoConfig(data=real_frame, image_dir=tmp_path, camera_time="pose").setup().parse()
    for a, b in zip(exp.cameras, pose.cameras):
        assert b.timestamps[0] == b.extras["pose_timestamp"][0]
        assert 0 < abs(a.timestamps[0] - b.timestamps[0]) < 0.02  # rolling-shutter centre vs pose time
        # FRONT reads out left to right: time of its principal point column
        if a.name == "FRONT":
            e = a.extras
            readout = e["camera_readout_done_time"][0] - e["camera_trigger_time"][0] - e["shutter"][0]
            cu = 949.5746451352071
            assert np.isclose(a.timestamps[0], e["camera_trigger_time"][0] + e["shutter"][0] / 2 + readout * cu / 1920)
