"""Round trip: a synthetic scene read by the ``processed`` reader vs the same scene written
as a Waymo segment (``omnire_waymo.writer``) and read by the ``waymo`` reader.

Tolerances: poses, boxes and sizes to 1e-9 (all stored as float64 in the protos; camera
poses 1e-6 m because the writer's exposure window [t - 2.5 ms, t + 2.5 ms] at Unix-epoch
magnitude rounds the centre time by up to 2.4e-7 s, extrapolated with the ego velocity);
timestamps to 1e-6 s; intrinsics exactly. LiDAR: ranges are float32 and azimuths are
binned to the range image's columns, so every point moves by at most half a column
(the writer uses 4 columns per azimuth step of the sweep: 0.05 degrees here): each
original point has a read-back point within range x sin(half a column) + 1e-4 m, and the
counts agree (one point per pixel).
"""
from __future__ import annotations

import shutil
import warnings

import numpy as np
import pytest
from scipy.spatial import cKDTree

from omnire.api import ConfigError, SceneDataError, spherical
from omnire_waymo import WaymoConfig
from omnire_waymo.tfrecord import TFRecordReader
from omnire_waymo.wod import dataset_pb2


def processed(path, **kw):
    from omnire_processed.reader import ProcessedDataparserConfig

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ProcessedDataparserConfig(data=path, scale=1.0, **kw).setup().parse()


def waymo(path, image_dir, **kw):
    return WaymoConfig(data=path, scale=1.0, image_dir=image_dir, **kw).setup().parse()


@pytest.fixture(scope="module")
def pair(synthetic, tmp_path_factory):
    proc_dir, seg_dir = synthetic
    return processed(proc_dir), waymo(seg_dir, tmp_path_factory.mktemp("img"))


def segment_file(seg_dir):
    (f,) = seg_dir.glob("*.tfrecord")
    return f


def compare(ref, got):
    assert got.num_frames == ref.num_frames >= 4
    assert np.abs((got.frame_timestamps - got.frame_timestamps[0]) - (ref.frame_timestamps - ref.frame_timestamps[0])).max() < 1e-6
    assert np.abs(got.ego_poses - ref.ego_poses).max() < 1e-9
    assert [c.name for c in got.cameras] == ["FRONT", "FRONT_LEFT", "FRONT_RIGHT"]
    for a, b in zip(ref.cameras, got.cameras):
        assert (a.width, a.height) == (b.width, b.height)
        assert np.array_equal(a.intrinsics, b.intrinsics)
        assert np.abs(a.cam_to_world - b.cam_to_world).max() < 1e-6
        t0 = got.frame_timestamps[0]
        assert np.abs((b.timestamps - t0) - (a.timestamps - ref.frame_timestamps[0])).max() < 1e-6
        assert np.array_equal(b.distortion, np.zeros(5))
        for pa, pb in zip(a.image_paths, b.image_paths):
            assert pa.read_bytes() == pb.read_bytes()  # the JPEGs travel unchanged
    ref_tracks = {t.track_id: t for t in ref.tracks}
    assert sorted(ref_tracks) == [t.track_id for t in got.tracks]
    for t in got.tracks:
        r = ref_tracks[t.track_id]
        assert np.array_equal(t.present, r.present) and t.category == r.category
        assert np.abs(t.poses[t.present] - r.poses[r.present]).max() < 1e-9
        assert np.abs(t.size - r.size).max() < 1e-9
        assert t.stationary == r.stationary
    for f in range(ref.num_frames):
        a = ref.lidar.points[f].astype(np.float64)
        b = got.lidar.points[f].astype(np.float64)
        assert len(a) == len(b) > 1000
        assert np.abs(got.lidar.origins[f] - ref.lidar.origins[f]).max() < 1e-9
        dist, _ = cKDTree(b).query(a)
        rng = np.linalg.norm(a - ref.lidar.origins[f], axis=1)
        half_column = np.deg2rad(0.4) / 4 / 2
        assert (dist <= rng * np.sin(half_column) * 1.0001 + 1e-4).all()


def test_round_trip_against_processed_reader(pair):
    compare(*pair)


def test_top_lidar_beams_intensity_and_pose(pair):
    """TOP returns carry their range-image row as beam, at the calibration's inclination
    seen from ``sensor_to_world`` (x forward: the TOP LiDAR's pose turned to the vehicle's
    heading); the writer stores intensity 0 (not simulated)."""
    _, got = pair
    lidar, model = got.lidar, got.lidar.beam_model
    assert model.name == "Waymo TOP" and model.num_beams > 8 and np.all(np.diff(model.elevations_deg) < 0)
    for f in lidar.available_frames():
        top = lidar.beams[f] >= 0
        assert top.mean() > 0.5 and (lidar.intensity[f] == 0).all()
        P = lidar.sensor_to_world[f]
        local = (lidar.points[f][top].astype(np.float64) - P[:3, 3]) @ P[:3, :3]
        _, _, el = spherical(local)
        assert np.abs(el - model.elevations_deg[lidar.beams[f][top]]).max() < 0.05
        forward = got.ego_poses[f][:3, 0]
        assert P[:3, 0] @ forward > np.cos(np.deg2rad(2.0))


def test_world_convention(pair):
    _, got = pair
    assert np.allclose(got.ego_poses[0], np.eye(4), atol=1e-9)  # origin and axes at the first ego pose
    assert got.ego_poses[-1, 0, 3] > 1.0  # the ego drives along +x
    # the front camera looks along +x with image-down = world-down (OpenCV axes)
    c2w = got.cameras[0].cam_to_world[0]
    assert c2w[0, 2] > 0.99 and c2w[2, 1] < -0.99


def test_segment_holds_what_the_format_says(synthetic):
    _, seg_dir = synthetic
    with TFRecordReader(segment_file(seg_dir)) as rd:
        frames = [dataset_pb2.Frame.FromString(p) for p in rd]
    f = frames[0]
    assert f.context.name == "omnire_synthetic_urban_seed0" and len(frames) == 8
    assert abs(f.pose.transform[3]) > 100  # a global frame, not the scene world
    assert [c.name for c in f.context.camera_calibrations] == [1, 2, 3]
    (lc,) = f.context.laser_calibrations
    assert lc.name == dataset_pb2.LaserName.TOP and len(lc.beam_inclinations) == 32
    assert np.allclose(np.rad2deg(lc.beam_inclinations), np.linspace(-25, 10, 32), atol=1e-4)
    (laser,) = f.lasers
    assert laser.ri_return1.range_image_pose_compressed and laser.ri_return2.range_image_compressed
    assert [im.name for im in f.images] == [1, 2, 3] and f.images[0].image[:2] == b"\xff\xd8"
    synced = [lab for lab in f.laser_labels if lab.HasField("camera_synced_box")]
    assert synced and all(lab.most_visible_camera_name in ("FRONT", "FRONT_LEFT", "FRONT_RIGHT") for lab in synced)
    assert all(lab.num_lidar_points_in_box >= 0 for lab in f.laser_labels)
    assert [fr.timestamp_micros - f.timestamp_micros for fr in frames] == [100_000 * i for i in range(8)]


def test_camera_synced_boxes_in_extras(pair):
    _, got = pair
    with_synced = [t for t in got.tracks if "camera_synced_box_to_world" in t.extras]
    assert with_synced
    for t in with_synced:
        e = t.extras
        has = np.isfinite(e["camera_synced_box_to_world"][:, 0, 0])
        assert has.any() and not has[~t.present].any()
        assert np.abs(e["camera_synced_box_to_world"][has] - t.poses[has]).max() < 1e-9  # synthetic: same time
        assert set(e["most_visible_camera"][has]) <= {"FRONT", "FRONT_LEFT", "FRONT_RIGHT"}
        assert np.allclose(e["camera_synced_size"][has], t.size)


def test_frame_range(synthetic, tmp_path):
    proc_dir, seg_dir = synthetic
    ref = processed(proc_dir, start_frame=2, end_frame=6)
    got = waymo(seg_dir, tmp_path, start_frame=2, end_frame=6)
    assert list(got.source_frames) == [2, 3, 4, 5]
    compare(ref, got)  # the world is anchored at frame 2 in both
    assert np.allclose(got.ego_poses[0], np.eye(4), atol=1e-9)
    with pytest.raises(ConfigError, match=r"frames 3\.\.3 .* select nothing of the 8 frames"):
        waymo(seg_dir, tmp_path, start_frame=3, end_frame=3)


def test_lidar_options(synthetic, tmp_path):
    _, seg_dir = synthetic
    full = waymo(seg_dir, tmp_path, end_frame=2)
    thin = waymo(seg_dir, tmp_path, end_frame=2, max_lidar_points_per_frame=500, lidar_returns=(1,))
    again = waymo(seg_dir, tmp_path, start_frame=1, end_frame=2, max_lidar_points_per_frame=500)
    assert len(thin.lidar.points[0]) == 500
    # thinning is seeded by the segment frame number: the same frame gives the same points
    # in any range (expressed in each range's world)
    w = again.ego_poses[0] @ np.linalg.inv(thin.ego_poses[1])
    moved = thin.lidar.points[1].astype(np.float64) @ w[:3, :3].T + w[:3, 3]
    assert np.abs(moved - again.lidar.points[0]).max() < 1e-3
    with pytest.warns(UserWarning, match="no range images"):
        none = waymo(seg_dir, tmp_path, end_frame=2, lidars=("FRONT",))
    assert none.lidar is None
    assert waymo(seg_dir, tmp_path, end_frame=2, load_lidar=False).lidar is None
    assert sum(len(p) for p in full.lidar.points) > 2 * 500
    with pytest.raises(ConfigError, match="lidars"):
        waymo(seg_dir, tmp_path, lidars=("ROOF",))
    with pytest.raises(ConfigError, match="lidar_returns"):
        waymo(seg_dir, tmp_path, lidar_returns=(3,))


def test_images_extracted_once(synthetic, tmp_path):
    _, seg_dir = synthetic
    s = waymo(seg_dir, tmp_path / "img", end_frame=2)
    path = s.cameras[0].image_paths[0]
    assert path.parent == tmp_path / "img"
    stamp = path.stat().st_mtime_ns
    waymo(seg_dir, tmp_path / "img", end_frame=2)
    assert path.stat().st_mtime_ns == stamp  # reused, not rewritten
    path.write_bytes(b"x")  # damaged cache entry: rewritten
    waymo(seg_dir, tmp_path / "img", end_frame=2)
    assert path.read_bytes()[:2] == b"\xff\xd8"
    with pytest.raises(ConfigError, match="inside the dataset folder"):
        waymo(seg_dir, seg_dir / "images")
    assert not (seg_dir / "images").exists()


# ----------------------------------------------------------------------------- errors
def copy_segment(seg_dir, tmp_path):
    dst = tmp_path / "seg"
    dst.mkdir()
    return shutil.copy(segment_file(seg_dir), dst / segment_file(seg_dir).name)


def test_error_damaged_record(synthetic, tmp_path):
    _, seg_dir = synthetic
    path = copy_segment(seg_dir, tmp_path)
    with TFRecordReader(path) as rd:
        spans = rd.index()
    data = bytearray(path.read_bytes())
    data[spans[3].offset + 12 + 1000] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(SceneDataError, match=rf"{path.name}: damaged record at byte offset {spans[3].offset}"):
        waymo(path, tmp_path / "img")
    waymo(path, tmp_path / "img", end_frame=3)  # frames before the damage still read


def test_error_not_a_frame(synthetic, tmp_path):
    from omnire_waymo.tfrecord import TFRecordWriter

    path = tmp_path / "bad.tfrecord"
    with TFRecordWriter(path) as w:
        w.write(b"\xff\xff\xff\xff not a protobuf")
    with pytest.raises(SceneDataError, match=r"bad\.tfrecord: record 0 \(byte offset 0\) is not a waymo.open_dataset.Frame"):
        waymo(path, tmp_path / "img")


def test_error_bad_range_image(synthetic, tmp_path):
    from omnire_waymo.tfrecord import TFRecordWriter

    _, seg_dir = synthetic
    with TFRecordReader(segment_file(seg_dir)) as rd:
        frame = dataset_pb2.Frame.FromString(next(iter(rd)))
    frame.lasers[0].ri_return2.range_image_compressed = b"not zlib"
    path = tmp_path / "x.tfrecord"
    with TFRecordWriter(path) as w:
        w.write(frame.SerializeToString())
    with pytest.raises(SceneDataError, match=r"x\.tfrecord: frame 0 \(record at byte offset 0\): "
                                             r"lasers\[TOP\]\.ri_return2\.range_image_compressed: not zlib"):
        waymo(path, tmp_path / "img")
    assert waymo(path, tmp_path / "img", lidar_returns=(1,)).lidar is not None


def test_error_missing_image_and_calibration(synthetic, tmp_path):
    from omnire_waymo.tfrecord import TFRecordWriter

    _, seg_dir = synthetic
    with TFRecordReader(segment_file(seg_dir)) as rd:
        frame = dataset_pb2.Frame.FromString(next(iter(rd)))
    del frame.images[1]
    path = tmp_path / "x.tfrecord"
    with TFRecordWriter(path) as w:
        w.write(frame.SerializeToString())
    with pytest.raises(SceneDataError, match=r"frame 0 .*images has no FRONT_LEFT image"):
        waymo(path, tmp_path / "img")
    frame.context.camera_calibrations[2].width = 100
    with TFRecordWriter(path) as w:
        w.write(frame.SerializeToString())
    with pytest.raises(SceneDataError, match=r"images\[FRONT_RIGHT\]\.image is 72x48 but its calibration says 100x48"):
        waymo(path, tmp_path / "img", cameras=("FRONT_RIGHT",))
    del frame.context.camera_calibrations[0].intrinsic[4:]
    with TFRecordWriter(path) as w:
        w.write(frame.SerializeToString())
    with pytest.raises(SceneDataError, match=r"camera_calibrations\[FRONT\]\.intrinsic: 4 values, expected 9"):
        waymo(path, tmp_path / "img", cameras=("FRONT",))


def test_error_data_paths(synthetic, tmp_path):
    _, seg_dir = synthetic
    with pytest.raises(FileNotFoundError, match="nope: Waymo segment not found"):
        waymo(tmp_path / "nope", tmp_path / "img")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no \\*.tfrecord segment"):
        waymo(tmp_path / "empty", tmp_path / "img")
    two = tmp_path / "two"
    two.mkdir()
    shutil.copy(segment_file(seg_dir), two / "a.tfrecord")
    shutil.copy(segment_file(seg_dir), two / "b.tfrecord")
    with pytest.raises(ConfigError, match="holds 2 segments \\(a.tfrecord, b.tfrecord\\)"):
        waymo(two, tmp_path / "img")
    (tmp_path / "empty.tfrecord").write_bytes(b"")
    with pytest.raises(SceneDataError, match="empty file"):
        waymo(tmp_path / "empty.tfrecord", tmp_path / "img")


def test_plugin_registered():
    from omnire.plugins import load_plugins

    plugins = load_plugins()
    assert plugins.dataparsers.get("waymo").config_factory is WaymoConfig
    assert plugins.scene_writers.get("waymo").write.__module__ == "omnire_waymo.writer"
    assert "bench waymo-read" in plugins.commands.names()
