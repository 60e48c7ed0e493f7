"""The reader's parts on real Argoverse 2 logs (../shared/data/av2: annotations, poses, LiDAR,
calibration; no images). Skipped when the data is absent."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from omnire.api import (
    SceneDataError, extend_poses, first_pose_world, loaded_intrinsics, points_in_sensor_frame, range_image, spherical,
)
from omnire_argoverse2 import log as av2
from omnire_argoverse2 import vlp32c
from omnire_argoverse2.dataparser import Argoverse2Config, Argoverse2Dataparser, load_lidar, load_tracks

AV2 = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "av2" / "sensor"
LOG_A = AV2 / "val" / "adcf7d18-0510-35b0-a2fa-b4cea13a6d76"  # 156 annotated sweeps, one LiDAR file, no calibration
LOG_B = AV2 / "val" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"  # calibration, two consecutive sweeps
LOG_B_TEST = AV2 / "test" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"  # the same log without annotations

pytestmark = pytest.mark.skipif(not LOG_B.is_dir(), reason="real AV2 fixtures (../shared/data/av2) not present")


def _frames(log: Path):
    ns, paths = av2.sweep_files(log)
    ego = av2.read_ego_poses(log)
    city_ego = ego.at(ns)
    return ns, paths, ego, city_ego, first_pose_world(city_ego[0])


@pytest.mark.parametrize("log", [LOG_A, LOG_B], ids=["adcf7d18", "7fab2350"])
def test_lidar_points_inside_boxes_match_num_interior_pts(log):
    """Boxes and LiDAR agree: at each sweep, the points inside each annotated box (pose,
    size, quaternion convention) are the count the annotation states."""
    ann = av2.read_annotations(log)
    ns, paths, *_ = _frames(log)
    for t, path in zip(ns, paths):
        rows = ann.at(t)
        assert len(rows) > 30
        sweep = av2.read_sweep(path)
        assert sweep.xyz.shape[0] > 90_000 and sweep.laser_number.max() <= 63
        counts = av2.points_in_boxes(sweep.xyz, ann.ego_SE3_box[rows], ann.size[rows])
        stated = ann.num_interior_pts[rows]
        assert np.mean(counts == stated) >= 0.98, (counts, stated)
        assert stated.sum() > 5000 and abs(counts.sum() - stated.sum()) <= 0.01 * stated.sum()
        # Swapping length and width (a wrong axis convention) breaks the agreement.
        swapped = av2.points_in_boxes(sweep.xyz, ann.ego_SE3_box[rows], ann.size[rows][:, [1, 0, 2]])
        assert np.mean(swapped == stated) < 0.8


def test_reader_tracks_and_lidar_agree_in_the_world():
    """The reader's own world chain (ego pose at the sweep x points, ego pose x cuboid) keeps
    every box around the same points as in the ego frame."""
    ann = av2.read_annotations(LOG_B)
    ns, paths, ego, city_ego, world = _frames(LOG_B)
    up = av2.read_sensor_poses(LOG_B)[av2.LIDAR_SENSOR]
    lidar = load_lidar(paths, ns, world[None] @ city_ego, up)
    tracks = load_tracks(ann, LOG_B / "annotations.feather", ns, ego, world)
    for f in range(len(ns)):
        present = [tr for tr in tracks if tr.extras["annotated"][f]]
        assert len(present) == len(ann.at(ns[f]))
        poses = np.stack([tr.poses[f] for tr in present])
        sizes = np.stack([tr.size for tr in present])
        counts = av2.points_in_boxes(lidar.points[f].astype(np.float64), poses, sizes)
        stated = np.array([tr.extras["num_interior_pts"][f] for tr in present])
        # float32 world points: a point on a face may flip; nearly all counts are exact.
        assert np.mean(counts == stated) >= 0.95
        assert np.abs(counts - stated).sum() <= 0.01 * stated.sum()
    # The first loaded ego pose is the origin, heading along +x, z up.
    ego0 = world @ city_ego[0]
    np.testing.assert_allclose(ego0[:3, 3], 0, atol=1e-9)
    assert ego0[0, 0] > 0.99 and abs(ego0[1, 0]) < 1e-9


@pytest.mark.parametrize("log", [LOG_A, LOG_B], ids=["adcf7d18", "7fab2350"])
def test_static_objects_stay_put_in_the_world(log):
    """Ego pose x cuboid chains correctly over the whole log: bollards, cones and signs move by
    metres in the ego frame while the ego drives, but stay within centimetres in the world."""
    ann = av2.read_annotations(log)
    ego = av2.read_ego_poses(log)
    frames = np.unique(ann.timestamps_ns)  # all 156 annotated sweeps as the frame clock
    world = first_pose_world(ego.at(frames[:1])[0])
    tracks = load_tracks(ann, log / "annotations.feather", frames, ego, world, max_track_gap=0.0)
    assert len(tracks) == len(np.unique(ann.track_uuid))
    static = [tr for tr in tracks if tr.class_name in ("BOLLARD", "CONSTRUCTION_CONE", "SIGN")
              and tr.present.sum() >= 20]
    assert len(static) >= 5
    for tr in static:
        assert tr.category == "other"
        centres = tr.poses[tr.present, :3, 3]
        assert np.linalg.norm(centres - np.median(centres, 0), axis=1).max() < 0.35, tr.track_id
        rows = np.flatnonzero(ann.track_uuid == tr.track_id)
        in_ego = ann.ego_SE3_box[rows, :3, 3]
        assert np.linalg.norm(in_ego - np.median(in_ego, 0), axis=1).max() > 3.0  # the ego did move
    assert np.mean([tr.stationary for tr in static]) >= 0.8
    # Presence follows the annotations exactly; categories follow the AV2 map.
    by_id = {tr.track_id: tr for tr in tracks}
    for uuid in np.unique(ann.track_uuid)[:20]:
        rows = np.flatnonzero(ann.track_uuid == uuid)
        assert by_id[uuid].present.sum() == len(rows)
    cats = {tr.class_name: tr.category for tr in tracks}
    assert cats.get("REGULAR_VEHICLE") == "vehicle" and cats.get("PEDESTRIAN") == "human"


@pytest.mark.parametrize("log", [LOG_A, LOG_B], ids=["adcf7d18", "7fab2350"])
def test_sweep_ground_lies_just_below_the_ego_origin(log):
    """Sweep points taken to the city frame with the ego pose at the sweep time put the road
    0.1-0.7 m below the ego origin (AV2's rear-axle centre)."""
    ns, paths, ego, city_ego, _ = _frames(log)
    for path, T in zip(paths, city_ego):
        xyz = av2.read_sweep(path, xyz_only=True).xyz
        ring = (np.linalg.norm(xyz[:, :2], axis=1) > 4) & (np.linalg.norm(xyz[:, :2], axis=1) < 15)
        z = (xyz[ring] @ T[:3, :3].T + T[:3, 3])[:, 2]
        hist, edges = np.histogram(z, bins=np.arange(z.min(), z.max() + 0.05, 0.05))
        ground = edges[np.argmax(hist)] + 0.025
        assert 0.0 < T[2, 3] - ground < 0.7, (T[2, 3], ground)


def test_consecutive_sweeps_align_after_ego_motion():
    """Two consecutive sweeps overlap in the city frame better than without the ego motion,
    or with it applied the wrong way round."""
    from scipy.spatial import cKDTree

    ns, paths, ego, city_ego, _ = _frames(LOG_B)
    a, b = (av2.read_sweep(p, xyz_only=True).xyz for p in paths)
    sel_b = (np.linalg.norm(b[:, :2], axis=1) > 10) & (np.linalg.norm(b[:, :2], axis=1) < 40)
    tree_city = cKDTree(a @ city_ego[0][:3, :3].T + city_ego[0][:3, 3])

    def residual(T_b):
        d, _ = tree_city.query(b[sel_b] @ T_b[:3, :3].T + T_b[:3, 3])
        return float(np.median(d))

    motion = np.linalg.inv(city_ego[0]) @ city_ego[1]  # ego(t1) in ego(t0)
    right = residual(city_ego[1])
    still = residual(city_ego[0])
    wrong = residual(city_ego[0] @ np.linalg.inv(motion))
    assert right < 0.06 and right < 0.8 * still and right < 0.6 * wrong, (right, still, wrong)


def test_calibration_of_all_cameras():
    """Intrinsics and extrinsics for all nine cameras: OpenCV axes in the ego frame, looking
    where each camera's name says, K with the +0.5 pixel-centre shift, radial distortion."""
    intr = av2.read_intrinsics(LOG_B)
    sensors = av2.read_sensor_poses(LOG_B)
    assert set(av2.RING_CAMERAS + av2.STEREO_CAMERAS) <= set(intr) <= set(sensors)
    assert {"up_lidar", "down_lidar"} <= set(sensors)
    yaw = {"ring_front_center": 0, "ring_front_left": 45, "ring_front_right": -45, "ring_side_left": 99,
           "ring_side_right": -99, "ring_rear_left": 153, "ring_rear_right": -153,
           "stereo_front_left": 0, "stereo_front_right": 0}
    for name, expected in yaw.items():
        T = sensors[name]
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) > 0.999
        assert R[:, 1] @ np.array([0.0, 0.0, -1.0]) > 0.99  # camera y (down) = ego -z
        got = np.degrees(np.arctan2(R[1, 2], R[0, 2]))  # optical axis (camera z) heading
        assert abs((got - expected + 180) % 360 - 180) < 10, (name, got)
        assert 1.1 < T[2, 3] < 1.5 and abs(T[0, 3]) < 2.0  # on the roof, ~1.4 m above the ego origin
        c = intr[name]
        assert (c.width, c.height) == ((1550, 2048) if name == "ring_front_center" else (2048, 1550))
        K = loaded_intrinsics(c.matrix, c.width, c.height, 0.5, "integer")[2]
        np.testing.assert_allclose(K[0], [c.fx / 2, 0, (c.cx + 0.5) / 2])
        np.testing.assert_allclose(c.distortion, [c.k1, c.k2, 0, 0, c.k3])
        assert -0.35 < c.k1 < -0.2  # barrel distortion of the wide lenses
    assert sensors["up_lidar"][2, 3] > 1.5
    # The test split carries the same calibration.
    assert np.allclose(av2.read_sensor_poses(LOG_B_TEST)["ring_front_left"], sensors["ring_front_left"])


def test_reader_names_the_missing_camera_folder(tmp_path):
    """The fixtures have no images: the reader says which camera folder is missing."""
    with pytest.raises(SceneDataError, match=r"sensors/cameras/ring_front_center: missing camera folder"):
        Argoverse2Dataparser(Argoverse2Config(data=LOG_B)).parse()
    with pytest.raises(SceneDataError, match=r"sensors/cameras/stereo_front_left: missing camera folder"):
        Argoverse2Dataparser(Argoverse2Config(data=LOG_B, cameras=("stereo_front_left",))).parse()
    # A split folder instead of a log: the message points at a log.
    with pytest.raises(SceneDataError, match="pass one of them"):
        Argoverse2Dataparser(Argoverse2Config(data=AV2 / "val")).parse()


def test_test_split_has_no_annotations_and_log_a_no_calibration():
    assert av2.read_annotations(LOG_B_TEST) is None
    with pytest.raises(SceneDataError, match=r"calibration/intrinsics.feather: missing camera intrinsics"):
        av2.read_intrinsics(LOG_A)


def test_reader_carries_intensity_times_and_sensor_pose():
    """Each point keeps its intensity (0-255 / 255) and time (sweep time + offset_ns, within
    one revolution of the sweep time); the sensor pose is up_lidar's at the sweep time."""
    ns, paths, ego, city_ego, world = _frames(LOG_B)
    up = av2.read_sensor_poses(LOG_B)[av2.LIDAR_SENSOR]
    lidar = load_lidar(paths, ns, world[None] @ city_ego, up, max_points=5000)
    for f, path in enumerate(paths):
        sweep = av2.read_sweep(path)
        assert len(lidar.points[f]) == 5000 and lidar.intensity[f].dtype == np.float32
        assert set(np.round(lidar.intensity[f] * 255).astype(int)) <= set(sweep.intensity.astype(int))
        dt = lidar.times[f] - ns[f] * 1e-9
        assert dt.min() >= sweep.offset_ns.min() * 1e-9 - 1e-6 and dt.max() <= sweep.offset_ns.max() * 1e-9 + 1e-6
        assert 0.05 < sweep.offset_ns.max() * 1e-9 - sweep.offset_ns.min() * 1e-9 < 0.12  # one revolution at 10 Hz
        np.testing.assert_allclose(lidar.sensor_to_world[f], world @ city_ego[f] @ up, atol=1e-9)


def test_up_lidar_lasers_are_the_vlp32c_datasheet_angles():
    """Each up_lidar laser number gets a datasheet angle of its own; in the sensor frame at
    their own time 99% of its returns lie within 0.1 degrees of it (measured 99.9-100%), the
    down_lidar's returns are beam -1, and the range image of a sweep is mostly returned."""
    ns, paths, ego, city_ego, world = _frames(LOG_B)
    up = av2.read_sensor_poses(LOG_B)[av2.LIDAR_SENSOR]
    lidar = load_lidar(paths, ns, world[None] @ city_ego, up)
    model = lidar.beam_model
    assert model.num_beams == 32 and model.num_azimuths == 1800
    np.testing.assert_array_equal(np.sort(model.elevations_deg), vlp32c.DATASHEET_ELEVATIONS_DEG)
    track = extend_poses(ns * 1e-9, lidar.sensor_to_world, 0.2)
    for f, path in enumerate(paths):
        lasers = av2.read_sweep(path).laser_number.astype(int)
        beams = lidar.beams[f]
        np.testing.assert_array_equal(beams, np.where(lasers < 32, lasers, -1))
        mine = beams >= 0
        rng, az, el = spherical(points_in_sensor_frame(lidar.points[f][mine].astype(np.float64),
                                                       lidar.times[f][mine], *track))
        assert np.mean(np.abs(el - model.elevations_deg[beams[mine]]) < 0.1) > 0.99
        assert range_image(rng, az, beams[mine], model).returned.mean() > 0.8


def test_sweeps_without_laser_numbers_get_no_beams():
    """A sweep whose returns do not show the 32 angles (every laser number 0) has no beams."""
    ns, paths, ego, city_ego, world = _frames(LOG_B)
    points = [np.asarray(av2.read_sweep(p).xyz, np.float64) for p in paths]
    times = [np.full(len(p), t * 1e-9) for p, t in zip(points, ns)]
    sensor = world[None] @ city_ego @ av2.read_sensor_poses(LOG_B)[av2.LIDAR_SENSOR][None]
    assert vlp32c.laser_elevations(points[0], times[0], np.zeros(len(points[0]), np.uint8), ns * 1e-9, sensor) is None
