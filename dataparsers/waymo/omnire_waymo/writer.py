"""Scene writer ``waymo``: a synthetic scene (processed layout) -> one Waymo v1 segment file.

``omnire synth urban out --tiny --format waymo`` writes
``out/segment-omnire_synthetic_<preset>_seed<seed>_with_camera_labels.tfrecord``: one
``waymo.open_dataset.Frame`` per frame, built with the dataset's own message definitions:

- Context: camera calibrations (intrinsics ``f_u f_v c_u c_v`` + the scene's distortion,
  extrinsics camera-to-vehicle in Waymo camera axes, size, global shutter) and the TOP LiDAR
  calibration (explicit beam inclinations found by clustering the points' inclinations;
  extrinsic = the sensor offset in the vehicle frame).
- Frame: ``timestamp_micros`` (the scene's frame times after an epoch offset), vehicle
  ``pose`` (the scene's ego pose in a global frame moved by an arbitrary rigid transform,
  which the reader's world anchoring must undo), the JPEG files unchanged as
  ``CameraImage.image`` with per-image pose, velocity and exposure fields.
- LiDAR: the points of each sweep binned into a TOP range image (rows = beams, columns =
  azimuth bins 4x finer than the sweep's azimuth step, so a point moves by at most half a
  bin, 1/8 of the step, in azimuth; range exact to float32), nearest point per pixel as the
  first return, the next as the second, with a per-pixel vehicle pose image.
- Labels: one ``laser_labels`` entry per present actor (upright box in the vehicle frame,
  type from its category, id = track id, speed, points in the box) with a camera-synced box
  (the same box: the synthetic cameras expose at the frame time) for the camera that sees
  its centre nearest to its optical axis.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from omnire.api import SceneDataError
from omnire_waymo import rangeimage
from omnire_waymo.dataparser import SYNTHETIC_PREFIX, WAYMO_TO_OPENCV
from omnire_waymo.tfrecord import TFRecordWriter
from omnire_waymo.wod import dataset_pb2, label_pb2

CAMERA_ORDER = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT", "REAR")
"""Waymo camera written for the synthetic camera ids 0..5 (front, front-left, front-right, left, right, back)."""
LABEL_TYPE = {"vehicle": "TYPE_VEHICLE", "human": "TYPE_PEDESTRIAN", "cyclist": "TYPE_CYCLIST", "other": "TYPE_UNKNOWN"}
EPOCH = 1_600_000_000
"""Seconds added to the scene's frame times (Waymo timestamps are Unix times)."""
GLOBAL_FROM_SCENE = np.array(
    [[np.cos(0.6), -np.sin(0.6), 0.0, 812.25], [np.sin(0.6), np.cos(0.6), 0.0, -433.5], [0.0, 0.0, 1.0, 17.0],
     [0.0, 0.0, 0.0, 1.0]]
)
"""Scene world -> the written global frame (arbitrary; readers anchor the world at the first pose)."""
SHUTTER = 0.005
AZIMUTH_OVERSAMPLING = 4
RIGID_TOLERANCE = 1e-5


def _set_transform(msg, M: np.ndarray) -> None:
    msg.transform.extend(np.asarray(M, dtype=np.float64).reshape(-1).tolist())


def _angular_velocity(R0: np.ndarray, R1: np.ndarray, dt: float) -> np.ndarray:
    """(3,) global-frame angular velocity w with R1 = exp([w] dt) R0."""
    D = R1 @ R0.T
    angle = np.arccos(np.clip((np.trace(D) - 1) / 2, -1.0, 1.0))
    if angle < 1e-12:
        return np.zeros(3)
    axis = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / (2 * np.sin(angle))
    return axis * angle / dt


def _velocities(times: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of (F, 4, 4) poses at (F,) times -> linear (F, 3), angular (F, 3)."""
    F = len(times)
    v, w = np.zeros((F, 3)), np.zeros((F, 3))
    if F < 2:
        return v, w
    for t in range(F):
        a, b = max(t - 1, 0), min(t + 1, F - 1)
        dt = times[b] - times[a]
        v[t] = (poses[b, :3, 3] - poses[a, :3, 3]) / dt
        w[t] = _angular_velocity(poses[a, :3, :3], poses[b, :3, :3], dt)
    return v, w


def _constant(values: np.ndarray, what: str) -> np.ndarray:
    """The mean of per-frame copies of what should be one rigid transform (checked)."""
    dev = np.abs(values - values[0]).max()
    if dev > RIGID_TOLERANCE:
        raise SceneDataError(
            f"{what} changes over the frames by up to {dev:.2e}; the Waymo layout has one fixed calibration per sensor"
        )
    return values.mean(axis=0)


def _scene_name(source: Path) -> str:
    try:
        gt = json.loads((source / "ground_truth.json").read_text())
        return f"{SYNTHETIC_PREFIX}_{gt['preset']}_seed{gt['seed']}"
    except (OSError, ValueError, KeyError, TypeError):
        return f"{SYNTHETIC_PREFIX}_{source.name}"


def _azimuth_step(points_sensor: np.ndarray, inclinations: np.ndarray) -> float:
    """Azimuth step (radians) of a spinning LiDAR from one sweep: median gap between
    consecutive azimuths along its most populated beam."""
    inc = np.arctan2(points_sensor[:, 2], np.hypot(points_sensor[:, 0], points_sensor[:, 1]))
    beam = np.abs(inc[:, None] - inclinations[None]).argmin(1)
    best = np.bincount(beam, minlength=len(inclinations)).argmax()
    az = np.sort(np.arctan2(points_sensor[beam == best, 1], points_sensor[beam == best, 0]))
    gaps = np.diff(az)
    gaps = gaps[gaps > 1e-7]
    return float(np.median(gaps)) if len(gaps) else 2 * np.pi / 2650


def write_scene(source: Path, output: Path) -> Path:
    """Convert the synthetic scene in ``source`` (processed layout) into one segment file in
    the existing, empty folder ``output``; returns the file's path."""
    from omnire_processed.reader import ProcessedDataparserConfig

    source, output = Path(source), Path(output)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # notes about the processed layout concern its reader only
        scene = ProcessedDataparserConfig(data=source, scale=1.0, holdout_every=0).setup().parse()
    if len(scene.cameras) > len(CAMERA_ORDER):
        raise SceneDataError(f"{source}: {len(scene.cameras)} cameras; the Waymo layout names at most {len(CAMERA_ORDER)}")
    F = scene.num_frames
    name = _scene_name(source)
    G = GLOBAL_FROM_SCENE
    ego = scene.ego_poses  # (F, 4, 4) vehicle -> scene world
    vehicle = G[None] @ ego  # (F, 4, 4) vehicle -> global
    times = scene.frame_timestamps - scene.frame_timestamps[0]
    v_lin, v_ang = _velocities(times, vehicle)
    inv_ego = np.linalg.inv(ego)

    context = dataset_pb2.Context(name=name)
    context.stats.time_of_day = "Day"
    context.stats.location = "omnire synthetic"
    context.stats.weather = "sunny"
    for i, cam in enumerate(scene.cameras):
        extr = _constant(inv_ego @ cam.cam_to_world @ np.linalg.inv(WAYMO_TO_OPENCV), f"camera {cam.name} extrinsic")
        cal = context.camera_calibrations.add()
        cal.name = dataset_pb2.CameraName.Name.Value(CAMERA_ORDER[i])
        K = cam.intrinsics
        dist = np.zeros(5) if cam.distortion is None else np.asarray(cam.distortion, dtype=np.float64)
        cal.intrinsic.extend([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist.tolist()])
        _set_transform(cal.extrinsic, extr)
        cal.width, cal.height = cam.width, cam.height
        cal.rolling_shutter_direction = dataset_pb2.CameraCalibration.GLOBAL_SHUTTER

    lidar = _lidar_setup(scene, inv_ego)
    if lidar is not None:
        cal = context.laser_calibrations.add()
        cal.name = dataset_pb2.LaserName.TOP
        cal.beam_inclinations.extend(lidar["inclinations"].tolist())
        cal.beam_inclination_min = float(lidar["inclinations"][0])
        cal.beam_inclination_max = float(lidar["inclinations"][-1])
        _set_transform(cal.extrinsic, lidar["extrinsic"])

    jpegs = [[Path(p) for p in cam.image_paths] for cam in scene.cameras]
    out = output / f"segment-{name}_with_camera_labels.tfrecord"
    dropped = 0
    with TFRecordWriter(out) as w:
        for t in range(F):
            frame = dataset_pb2.Frame()
            frame.context.CopyFrom(context)
            frame.timestamp_micros = EPOCH * 1_000_000 + int(round(times[t] * 1e6))
            _set_transform(frame.pose, vehicle[t])
            for i, cam in enumerate(scene.cameras):
                data = jpegs[i][t].read_bytes()
                if data[:2] != b"\xff\xd8":
                    raise SceneDataError(f"{jpegs[i][t]}: not a JPEG; Waymo frames embed JPEG images")
                t_img = EPOCH + (cam.timestamps[t] - scene.frame_timestamps[0])
                im = frame.images.add()
                im.name = dataset_pb2.CameraName.Name.Value(CAMERA_ORDER[i])
                im.image = data
                _set_transform(im.pose, vehicle[t])
                im.velocity.v_x, im.velocity.v_y, im.velocity.v_z = v_lin[t].tolist()
                im.velocity.w_x, im.velocity.w_y, im.velocity.w_z = v_ang[t].tolist()
                im.pose_timestamp = t_img
                im.shutter = SHUTTER
                im.camera_trigger_time = t_img - SHUTTER / 2
                im.camera_readout_done_time = t_img + SHUTTER / 2
            pts = None
            if lidar is not None and scene.lidar.points[t] is not None:
                pts = scene.lidar.points[t].astype(np.float64)
                dropped += _add_lidar(frame, lidar, inv_ego[t], vehicle[t], pts)
            _add_labels(frame, scene, t, ego[t], inv_ego[t], times, pts)
            w.write(frame.SerializeToString())
    if dropped:
        warnings.warn(f"{out}: {dropped} LiDAR points dropped (a third or later return in one range image pixel)", stacklevel=2)
    return out


def _lidar_setup(scene, inv_ego: np.ndarray):
    """TOP LiDAR calibration from the sweeps: extrinsic (sensor offset in the vehicle frame,
    vehicle axes), ascending beam inclinations, range image width. None without LiDAR."""
    if scene.lidar is None or not scene.lidar.available_frames():
        return None
    frames = scene.lidar.available_frames()
    offsets = np.stack([(inv_ego[t] @ np.append(scene.lidar.origins[t], 1.0))[:3] for t in frames])
    E = np.eye(4)
    E[:3, 3] = _constant(offsets, "LiDAR origin in the vehicle frame")
    sensor_pts, incl = [], []
    for t in frames:
        S = np.linalg.inv(scene.ego_poses[t] @ E)
        p = scene.lidar.points[t].astype(np.float64) @ S[:3, :3].T + S[:3, 3]
        sensor_pts.append(p)
        incl.append(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    beams = rangeimage.cluster_inclinations(np.concatenate(incl))
    if len(beams) > 1024:
        raise SceneDataError(f"LiDAR points do not form beams ({len(beams)} distinct inclinations); cannot build a range image")
    step = _azimuth_step(sensor_pts[0], beams)
    width = int(min(8192, AZIMUTH_OVERSAMPLING * max(1, round(2 * np.pi / step))))
    return {"extrinsic": E, "inclinations": beams, "width": width}


def _add_lidar(frame, lidar: dict, inv_ego_t: np.ndarray, vehicle_t: np.ndarray, pts_world: np.ndarray) -> int:
    E = lidar["extrinsic"]
    S = np.linalg.inv(E) @ inv_ego_t  # scene world -> sensor
    p = pts_world @ S[:3, :3].T + S[:3, 3]
    first, second, dropped = rangeimage.points_to_range_images(p, lidar["inclinations"], lidar["width"])
    H, W = first.shape
    roll, pitch, yaw = rangeimage.rotmat_to_euler(vehicle_t[:3, :3])
    pose_img = np.empty((H, W, 6), np.float32)
    pose_img[:] = np.array([roll, pitch, yaw, *vehicle_t[:3, 3]], dtype=np.float64)
    laser = frame.lasers.add()
    laser.name = dataset_pb2.LaserName.TOP
    for ri, ranges in ((laser.ri_return1, first), (laser.ri_return2, second)):
        img = np.full((H, W, 4), -1.0, np.float32)  # no return: -1 in every channel
        hit = ranges > 0
        img[hit, 0] = ranges[hit]
        img[hit, 1] = 0.0  # intensity and elongation are not simulated
        img[hit, 2] = 0.0
        ri.range_image_compressed = rangeimage.encode_matrix_float(img)
    laser.ri_return1.range_image_pose_compressed = rangeimage.encode_matrix_float(pose_img)
    return dropped


def _add_labels(frame, scene, t: int, ego_t: np.ndarray, inv_ego_t: np.ndarray, times: np.ndarray,
                pts_world) -> None:
    F = scene.num_frames
    for track in scene.tracks:
        if not track.present[t]:
            continue
        B = inv_ego_t @ track.poses[t]  # box -> vehicle
        if abs(B[2, 2] - 1.0) > 1e-6:
            warnings.warn(f"track {track.track_id}: box not upright in the vehicle frame at frame {t}; "
                          "Waymo boxes are upright, the tilt is dropped", stacklevel=3)
        lab = frame.laser_labels.add()
        lab.id = track.track_id
        lab.type = label_pb2.Label.Type.Value(LABEL_TYPE.get(track.category, "TYPE_UNKNOWN"))
        _set_box(lab.box, B, track.size)
        # Speed: finite difference over present neighbours, in the vehicle frame.
        a = t - 1 if t > 0 and track.present[t - 1] else t
        b = t + 1 if t + 1 < F and track.present[t + 1] else t
        if b > a:
            vel = (track.poses[b, :3, 3] - track.poses[a, :3, 3]) / (times[b] - times[a])
            lab.metadata.speed_x, lab.metadata.speed_y, lab.metadata.speed_z = (inv_ego_t[:3, :3] @ vel).tolist()
        if pts_world is not None:
            local = (pts_world - track.poses[t, :3, 3]) @ track.poses[t, :3, :3]
            n = int((np.abs(local) <= track.size / 2).all(axis=1).sum())
            lab.num_lidar_points_in_box = n
            lab.num_top_lidar_points_in_box = n
        cam = _most_visible_camera(scene, t, track.poses[t, :3, 3])
        if cam is not None:
            lab.most_visible_camera_name = CAMERA_ORDER[cam]
            _set_box(lab.camera_synced_box, B, track.size)


def _set_box(box, B: np.ndarray, size: np.ndarray) -> None:
    box.center_x, box.center_y, box.center_z = B[:3, 3].tolist()
    box.heading = float(np.arctan2(B[1, 0], B[0, 0]))
    box.length, box.width, box.height = (float(s) for s in size)


def _most_visible_camera(scene, t: int, centre: np.ndarray):
    """Index of the camera whose image holds the box centre nearest its optical axis (or None)."""
    best, best_angle = None, np.inf
    for i, cam in enumerate(scene.cameras):
        w2c = np.linalg.inv(cam.cam_to_world[t])
        p = w2c[:3, :3] @ centre + w2c[:3, 3]
        if p[2] <= 0.1:
            continue
        u, v = (cam.intrinsics @ p)[:2] / p[2]
        if not (0 <= u < cam.width and 0 <= v < cam.height):
            continue
        angle = np.arctan2(np.hypot(p[0], p[1]), p[2])
        if angle < best_angle:
            best, best_angle = i, angle
    return best


__all__ = ["CAMERA_ORDER", "GLOBAL_FROM_SCENE", "write_scene"]
