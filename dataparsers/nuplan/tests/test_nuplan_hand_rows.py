"""The nuPlan reader on a database written here by hand: a few rows following the devkit's
schema, with values chosen so the camera, box and point poses can be worked out on paper.

Conventions used for the expected values, and where nuplan-devkit documents each:

- tokens are 8-byte BLOBs, calibration cells are pickled lists of the devkit's
  ``data_types.Translation`` / ``Rotation`` / ``CameraIntrinsic`` (list subclasses):
  ``nuplan/database/common/sql_types.py`` (HexLen8, SimplePickleType) and the CREATE TABLE
  statements of ``nuplan/database/nuplan_db/test/minimal_db_test_utils.py``;
- quaternions are (w, x, y, z): ``docs/nuplan_schema.md`` (camera / lidar ``rotation``),
  ``nuplan/database/nuplan_db_orm/ego_pose.py`` (``Quaternion(qw, qx, qy, qz)``);
- ego_pose is ego -> global, camera / lidar rows are sensor -> ego, merged clouds are in the
  lidar row's frame: ``nuplan_db_orm/rendering_utils.py`` ``map_pointcloud_to_image``
  (points -> image by ``camera.trans_matrix_inv @ ego_pose(image).trans_matrix_inv @
  ego_pose(lidar_pc).trans_matrix @ lidar.trans_matrix``), and ``nuplan_db_orm/image.py``
  ``Image.boxes`` -> ``utils.py`` ``get_boxes`` (global boxes moved by
  ``ego_pose.trans_matrix_inv`` then ``camera.trans_matrix_inv``);
- the camera frame is OpenCV's (z forward, divided by in ``utils/geometry.py`` ``view_points``);
  K's pixel centres are at integers (``rendering_utils.py`` ``render_pointcloud_in_image``
  scatters K-projected points over ``imshow``), so omnire's cx, cy are K's + 0.5;
  distortion is (k1, k2, p1, p2, k3) (``docs/nuplan_schema.md``, camera);
- lidar_box x, y, z are global, the rotation is ``yaw`` about z only
  (``nuplan_db_orm/lidar_box.py`` ``LidarBox.rotation``), size is (width, length, height)
  (``LidarBox.size``) with the length along the box's x (``utils/boxes/box3d.py``
  ``Box3D._calc_corners``);
- timestamps are microseconds (``nuplan_db/nuplan_scenario_queries.py``
  ``get_images_from_lidar_tokens``: 50000 us = 0.05 s), lidar_pc at 20 Hz;
- merged point clouds are binary ``.pcd`` (``utils/pointclouds/pointcloud.py``
  ``PointCloud.parse``).
"""
from __future__ import annotations

import math
import pickle
import sqlite3
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from omnire_nuplan import NuPlanConfig, NuPlanDataError, parse_pcd, read_points

R2 = math.sqrt(0.5)
T0 = 1_620_000_000_000_000  # microseconds
DDL = {
    "log": "token BLOB, vehicle_name TEXT, date TEXT, timestamp INTEGER, logfile TEXT, location TEXT, map_version TEXT",
    "ego_pose": "token BLOB, timestamp INTEGER, x FLOAT, y FLOAT, z FLOAT, qw FLOAT, qx FLOAT, qy FLOAT, qz FLOAT, "
                "epsg INTEGER, log_token BLOB",
    "camera": "token BLOB, log_token BLOB, channel TEXT, model TEXT, translation BLOB, rotation BLOB, intrinsic BLOB, "
              "distortion BLOB, width INTEGER, height INTEGER",
    "image": "token BLOB, next_token BLOB, prev_token BLOB, ego_pose_token BLOB, camera_token BLOB, "
             "filename_jpg TEXT, timestamp INTEGER",
    "lidar": "token BLOB, log_token BLOB, channel TEXT, model TEXT, translation BLOB, rotation BLOB",
    "lidar_pc": "token BLOB, next_token BLOB, prev_token BLOB, ego_pose_token BLOB, lidar_token BLOB, scene_token BLOB, "
                "filename TEXT, timestamp INTEGER",
    "lidar_box": "token BLOB, lidar_pc_token BLOB, track_token BLOB, next_token BLOB, prev_token BLOB, x FLOAT, "
                 "y FLOAT, z FLOAT, width FLOAT, length FLOAT, height FLOAT, vx FLOAT, vy FLOAT, vz FLOAT, yaw FLOAT, "
                 "confidence FLOAT",
    "track": "token BLOB, category_token BLOB, width FLOAT, length FLOAT, height FLOAT",
    "category": "token BLOB, name TEXT, description TEXT",
}


def tok(n: int) -> bytes:
    return n.to_bytes(8, "big")


@pytest.fixture
def devkit_types(monkeypatch):
    """The devkit's list subclasses under their own module name, so the calibration cells are
    pickled exactly as the devkit pickles them (the reader itself never imports the devkit)."""
    mod = types.ModuleType("nuplan.database.common.data_types")
    for name in ("Translation", "Rotation", "CameraIntrinsic"):
        cls = type(name, (list,), {"__module__": mod.__name__})
        setattr(mod, name, cls)
    for parent in ("nuplan", "nuplan.database", "nuplan.database.common"):
        monkeypatch.setitem(sys.modules, parent, types.ModuleType(parent))
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    return mod


def write_log(root: Path, dt, image_at: int = 0) -> Path:
    """A log: two lidar_pc 50 ms apart, ego at (100, 200, 0) heading +90 degrees (global y), one
    CAM_F0 image at lidar_pc ``image_at``'s time, one car box, one LiDAR point per sweep."""
    import OpenImageIO as oiio

    db = root / "nuplan-v1.1" / "splits" / "mini" / "hand.db"
    blobs = root / "nuplan-v1.1" / "sensor_blobs"
    (blobs / "hand" / "CAM_F0").mkdir(parents=True)
    (blobs / "hand" / "MergedPointCloud").mkdir(parents=True)
    db.parent.mkdir(parents=True)
    img = blobs / "hand" / "CAM_F0" / "a.jpg"
    out = oiio.ImageOutput.create(str(img))
    out.open(str(img), oiio.ImageSpec(64, 48, 3, "uint8"))
    out.write_image(np.full((48, 64, 3), 128, np.uint8))
    out.close()
    header = ("VERSION 0.7\nFIELDS x y z intensity ring lidar_info\nSIZE 4 4 4 4 4 4\nTYPE F F F F F F\n"
              "COUNT 1 1 1 1 1 1\nWIDTH 1\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA binary\n").encode()
    for k in range(2):
        point = np.array([(1.0, 0.0, 0.0, 77.0, 3.0, 1.0)], dtype=[(n, "<f4") for n in
                                                                   ("x", "y", "z", "intensity", "ring", "lidar_info")])
        (blobs / "hand" / "MergedPointCloud" / f"{k}.pcd").write_bytes(header + point.tobytes() + b"\0" * 7)
    conn = sqlite3.connect(db)
    for table, body in DDL.items():
        conn.execute(f"CREATE TABLE {table} ({body})")
    ins = lambda table, *row: conn.execute(f"INSERT INTO {table} VALUES ({','.join('?' * len(row))})", row)
    ins("log", tok(1), "veh", "2021-05-14", T0, "hand", "here", "v")
    for k in range(2):  # ego at (100, 200, 0), yaw +90 degrees: (qw, qz) = (cos 45, sin 45)
        ins("ego_pose", tok(10 + k), T0 + 50_000 * k, 100.0, 200.0, 0.0, R2, 0.0, 0.0, R2, 32611, tok(1))
    ins("ego_pose", tok(20), T0 + 50_000 * image_at, 100.0, 200.0, 0.0, R2, 0.0, 0.0, R2, 32611, tok(1))
    # CAM_F0 1 m ahead, 1.5 m up, looking forward: camera axes x, y, z = ego -y, -z, +x;
    # that rotation's quaternion (w, x, y, z) is (0.5, -0.5, 0.5, -0.5).
    ins("camera", tok(30), tok(1), "CAM_F0", "m", pickle.dumps(dt.Translation([1.0, 0.0, 1.5]), protocol=0),
        pickle.dumps(dt.Rotation([0.5, -0.5, 0.5, -0.5])),
        pickle.dumps(dt.CameraIntrinsic([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])),
        pickle.dumps([-0.3, 0.1, 0.001, -0.002, 0.0]), 64, 48)
    ins("image", tok(40), None, None, tok(20), tok(30), "hand/CAM_F0/a.jpg", T0 + 50_000 * image_at)
    # MergedPointCloud 0.5 m ahead, 2 m up, axes of the ego (rotation (1, 0, 0, 0)).
    ins("lidar", tok(50), tok(1), "MergedPointCloud", "m", pickle.dumps(dt.Translation([0.5, 0.0, 2.0])),
        pickle.dumps(dt.Rotation([1.0, 0.0, 0.0, 0.0])))
    for k in range(2):
        ins("lidar_pc", tok(60 + k), None, None, tok(10 + k), tok(50), tok(2), f"hand/MergedPointCloud/{k}.pcd",
            T0 + 50_000 * k)
    ins("category", tok(70), "vehicle", "cars")
    ins("track", tok(80), tok(70), 2.0, 4.5, 1.6)
    # A car at global (110, 205, 0.8) heading global -x (yaw pi); width 2, length 4.5, height 1.6.
    for k in range(2):
        ins("lidar_box", tok(90 + k), tok(60 + k), tok(80), None, None, 110.0, 205.0, 0.8, 2.0, 4.5, 1.6,
            0.0, 0.0, 0.0, math.pi, 0.9)
    conn.commit()
    conn.close()
    return db


def test_hand_rows_give_the_hand_computed_poses(tmp_path, devkit_types):
    db = write_log(tmp_path, devkit_types)
    scene = NuPlanConfig(data=db, scale=0.5, holdout_every=0).setup().parse()
    assert scene.num_frames == 1 and scene.source_frames.tolist() == [0]
    assert scene.frame_timestamps[0] == T0 * 1e-6
    # World: origin at the ego, x along its heading (global +y), z up: global (x, y) ->
    # world (y - 200, 100 - x). The ego is the identity there.
    assert np.allclose(scene.ego_poses[0], np.eye(4), atol=1e-12)
    cam = scene.cameras[0]
    assert cam.name == "CAM_F0" and (cam.width, cam.height) == (32, 24)
    # K: +0.5 px for omnire's pixel centres, then half size: fx 25, cx (31.5 + 0.5) / 2 = 16.
    assert np.allclose(cam.intrinsics, [[25.0, 0.0, 16.0], [0.0, 25.0, 12.0], [0.0, 0.0, 1.0]], atol=1e-12)
    assert np.allclose(cam.distortion, [-0.3, 0.1, 0.001, -0.002, 0.0])
    # Camera 1 m ahead of the ego and 1.5 m up; x right = world -y, y down = world -z, z = world +x.
    assert np.allclose(cam.cam_to_world[0], [[0, 0, 1, 1.0], [-1, 0, 0, 0.0], [0, -1, 0, 1.5], [0, 0, 0, 1]],
                       atol=1e-12)
    # The car: global offset (10, 5, 0.8) from the ego -> world (5, -10, 0.8); heading global -x
    # -> world +y, so its x axis is world +y; size (length, width, height).
    (car,) = scene.tracks
    assert car.category == "vehicle" and car.class_name == "vehicle" and car.track_id == tok(80).hex()
    assert np.allclose(car.poses[0], [[0, -1, 0, 5.0], [1, 0, 0, -10.0], [0, 0, 1, 0.8], [0, 0, 0, 1]], atol=1e-12)
    assert np.allclose(car.size, [4.5, 2.0, 1.6])
    # The point (1, 0, 0) of the sweep: lidar frame -> ego (1.5, 0, 2) -> world (1.5, 0, 2).
    assert np.allclose(scene.lidar.points[0], [[1.5, 0.0, 2.0]], atol=1e-6)
    assert np.allclose(scene.lidar.origins[0], [0.5, 0.0, 2.0])


def test_phase_follows_the_images(tmp_path, devkit_types):
    """With the image at the second sweep's time, the frame is the second sweep (the reference
    shifts to the interleaved lidar_pc sequence that meets the images)."""
    scene = NuPlanConfig(data=write_log(tmp_path, devkit_types, image_at=1), holdout_every=0).setup().parse()
    assert scene.source_frames.tolist() == [1] and scene.frame_timestamps[0] == (T0 + 50_000) * 1e-6
    every = NuPlanConfig(data=tmp_path, frame_step=1, holdout_every=0).setup().parse()
    assert every.num_frames == 2 and [t.present.tolist() for t in every.tracks] == [[True, True]]


def test_pcd_records_and_trailing_bytes(tmp_path, devkit_types):
    write_log(tmp_path, devkit_types)
    path = tmp_path / "nuplan-v1.1" / "sensor_blobs" / "hand" / "MergedPointCloud" / "0.pcd"
    rec = parse_pcd(path.read_bytes(), path)
    assert rec.tolist() == [(1.0, 0.0, 0.0, 77.0, 3.0, 1.0)]  # the 7 trailing bytes are ignored, as the devkit does
    mixed = (b"# comment\nVERSION 0.7\nFIELDS x y z t\nSIZE 4 4 4 8\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\n"
             b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA binary\n"
             + np.array([(1, 2, 3, 9), (4, 5, 6, 10)], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                                              ("t", "<u8")]).tobytes())
    rec = parse_pcd(mixed, Path("mixed.pcd"))
    assert rec["z"].tolist() == [3.0, 6.0] and rec["t"].tolist() == [9, 10]
    bin2 = tmp_path / "c.bin2"  # the devkit's other merged-cloud blob: 6 float32 columns
    bin2.write_bytes(np.arange(12, dtype="<f4").tobytes())
    assert read_points(bin2)["lidar_info"].tolist() == [5.0, 11.0]
    with pytest.raises(NuPlanDataError, match=r"mixed.pcd: .pcd POINTS 3 needs 60 bytes"):
        parse_pcd(mixed.replace(b"POINTS 2", b"POINTS 3"), Path("mixed.pcd"))
    with pytest.raises(NuPlanDataError, match="DATA ascii; nuPlan blobs are DATA binary"):
        parse_pcd(mixed.replace(b"DATA binary", b"DATA ascii"), Path("mixed.pcd"))
