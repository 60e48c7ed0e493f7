"""Scene writer ``nuplan``: a synthetic scene (``omnire synth``) as a nuPlan log, so the reader
is tested on logs where every pose, box and point is known.

What is written (``<output>/``), as the nuPlan release lays a log out (schema: nuplan-devkit
``docs/nuplan_schema.md``; column types as in ``nuplan/database/nuplan_db/test/
minimal_db_test_utils.py``)::

    nuplan-v1.1/splits/mini/<LOG>.db                         SQLite: log, scene, ego_pose, camera,
                                                             image, lidar, lidar_pc, lidar_box, track,
                                                             category, scenario_tag, traffic_light_status
    nuplan-v1.1/sensor_blobs/<LOG>/<CAM>/<token>.jpg         images (JPEG bytes copied unchanged)
    nuplan-v1.1/sensor_blobs/<LOG>/MergedPointCloud/<token>.pcd
    ground_truth.npz/.json    the generator's ground truth (not part of the layout)

- Tokens are 8-byte BLOBs; calibration lists are pickled plain lists (protocol 2).
- Clock: lidar_pc rows at twice the synthetic frame rate (20 Hz for 10 fps, as nuPlan):
  the even ones at the frame times, the odd ones half-way between. An in-between sweep holds
  the points of the frame before it, re-expressed in its own (interpolated) sensor pose, and
  boxes interpolated between the two frames (present only where the actor is on both), so
  only the even sweeps are exact; the reader's default ``--frame-step 2`` picks them (they
  lie on the image times). Images: one per camera per frame, at the frame time (10 Hz).
- Every image and lidar_pc has its own ego_pose row (z and tilt of the generator kept), in a
  global frame = generator world turned and shifted to UTM-sized coordinates.
- Cameras: synthetic cameras 0..7 are CAM_F0, CAM_L0, CAM_R0, CAM_L1, CAM_R1, CAM_L2, CAM_R2,
  CAM_B0; intrinsic in the integer-pixel-centre convention (cx, cy = ours - 0.5); distortion
  all zero (the synthetic images are pinhole).
- MergedPointCloud: one ``lidar`` row (at the synthetic sensor's position, turned about its z
  axis: a tilt would take the rings off the cones of the written frame, which must be the top
  LiDAR's own for the reader to measure its beams); ``.pcd`` binary with float32 x y z
  intensity (0-255) ring lidar_info, as merged clouds hold them (omnire_nuplan/lidars.py):
  the synthetic LiDAR is the top LiDAR (lidar_info 0, ring = its beam, numbered by ascending
  elevation as the generator spaces them), except its returns in the :data:`BACK_SECTOR_DEG`
  azimuths (sensor frame), written as the back LiDAR's (lidar_info 3, its own ring numbering:
  beams top to bottom).
- lidar_box: global centre, yaw, width / length / height, velocity from the neighbouring
  sweeps, confidence 1; tracks with their category (vehicle, pedestrian, bicycle).
"""
from __future__ import annotations

import hashlib
import pickle
import sqlite3
import tempfile
from pathlib import Path

import numpy as np

from omnire.api import (
    BeamModel,
    UserError,
    assign_beams,
    atomic_write_bytes,
    axis_rotation,
    interpolate_poses,
    interpolate_track,
    rotmat_to_quat,
    spherical,
)
from omnire_nuplan.dataparser import CAMERAS
from omnire_nuplan.pointcloud import write_pcd
from omnire.api import BYTE_INTENSITY, rigid
from omnire_processed.groundtruth import SyntheticSource

LOG = "2021.06.07.12.54.00_veh-99_00001_00100"
"""Log name (a real one's form: date, vehicle, start and end sweep); veh-99 marks it synthetic."""
GLOBAL_FROM_GENERATOR = rigid(axis_rotation(2, 0.4), (664180.25, 3997120.75, 606.5))
"""Generator world -> the written global frame (UTM-sized, as nuPlan's): a turn and a shift."""
LIDAR_TO_EGO_ROTATION = axis_rotation(2, 0.02)
"""Rotation of the written MergedPointCloud frame in the ego frame (a small turn about z)."""
BACK_SECTOR_DEG = (160.0, 200.0)
"""Azimuths (sensor frame, degrees) whose synthetic returns are written as the back LiDAR's."""
BACK_LIDAR = 3
"""``lidar_info`` of the back LiDAR (nuplan-devkit's numbering, omnire_nuplan/lidars.py)."""
FIRST_US = 1623070440050112
CATEGORIES = ("vehicle", "bicycle", "pedestrian", "traffic_cone", "barrier", "czone_sign", "generic_object")
"""The nuPlan categories (nuplan-devkit minimal_db_test_utils.py, schema 'category')."""
CATEGORY_OF_KIND = {"car": "vehicle", "pedestrian": "pedestrian", "cyclist": "bicycle"}

SCHEMA = {
    "log": "token BLOB NOT NULL, vehicle_name VARCHAR(64), date VARCHAR(64), timestamp INTEGER, "
           "logfile VARCHAR(64), location VARCHAR(64), map_version VARCHAR(64)",
    "scene": "token BLOB NOT NULL, log_token BLOB NOT NULL, name TEXT, goal_ego_pose_token BLOB, roadblock_ids TEXT",
    "ego_pose": "token BLOB NOT NULL, timestamp INTEGER, x FLOAT, y FLOAT, z FLOAT, qw FLOAT, qx FLOAT, qy FLOAT, "
                "qz FLOAT, vx FLOAT, vy FLOAT, vz FLOAT, acceleration_x FLOAT, acceleration_y FLOAT, "
                "acceleration_z FLOAT, angular_rate_x FLOAT, angular_rate_y FLOAT, angular_rate_z FLOAT, "
                "epsg INTEGER, log_token BLOB NOT NULL",
    "camera": "token BLOB NOT NULL, log_token BLOB NOT NULL, channel VARCHAR(64), model VARCHAR(64), "
              "translation BLOB, rotation BLOB, intrinsic BLOB, distortion BLOB, width INTEGER, height INTEGER",
    "image": "token BLOB NOT NULL, next_token BLOB, prev_token BLOB, ego_pose_token BLOB NOT NULL, "
             "camera_token BLOB NOT NULL, filename_jpg VARCHAR(128), timestamp INTEGER",
    "lidar": "token BLOB NOT NULL, log_token BLOB NOT NULL, channel VARCHAR(64), model VARCHAR(64), "
             "translation BLOB, rotation BLOB",
    "lidar_pc": "token BLOB NOT NULL, next_token BLOB, prev_token BLOB, ego_pose_token BLOB NOT NULL, "
                "lidar_token BLOB NOT NULL, scene_token BLOB, filename VARCHAR(128), timestamp INTEGER",
    "lidar_box": "token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL, track_token BLOB NOT NULL, next_token BLOB, "
                 "prev_token BLOB, x FLOAT, y FLOAT, z FLOAT, width FLOAT, length FLOAT, height FLOAT, vx FLOAT, "
                 "vy FLOAT, vz FLOAT, yaw FLOAT, confidence FLOAT",
    "track": "token BLOB NOT NULL, category_token BLOB NOT NULL, width FLOAT, length FLOAT, height FLOAT",
    "category": "token BLOB NOT NULL, name VARCHAR(64), description TEXT",
    "scenario_tag": "token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL, type TEXT, agent_track_token BLOB",
    "traffic_light_status": "token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL, lane_connector_id INTEGER, "
                            "status VARCHAR(8)",
}
"""CREATE TABLE bodies (column order and types as in the devkit's test databases), each with PRIMARY KEY (token)."""


def token(*parts) -> bytes:
    """A deterministic 8-byte token (nuPlan tokens are 8-byte BLOBs)."""
    return hashlib.md5(":".join(map(str, parts)).encode()).digest()[:8]


def database_path(output: Path) -> Path:
    return Path(output) / "nuplan-v1.1" / "splits" / "mini" / f"{LOG}.db"


def blobs_path(output: Path) -> Path:
    return Path(output) / "nuplan-v1.1" / "sensor_blobs"


def load_source(source: Path) -> SyntheticSource:
    """The synthetic scene the writer converts (the one place the writer gets its source)."""
    return SyntheticSource.load(Path(source))


def write_scene(source: Path, output: Path) -> None:
    """Scene-writer entry point (``omnire synth --format nuplan``)."""
    write_nuplan(load_source(source), Path(output))


def write_nuplan(src: SyntheticSource, output: Path) -> dict:
    """Write ``src`` as a nuPlan log into ``output`` (layout in the module docstring).
    Returns a summary (frames, sweeps, channels, first timestamp)."""
    F, C = src.num_frames, len(src.scene.cameras)
    if C > len(CAMERAS):
        raise UserError(f"{src.source}: {C} cameras; nuPlan has {len(CAMERAS)}")
    channels = CAMERAS[:C]
    rows: dict[str, list[tuple]] = {name: [] for name in SCHEMA}
    log_tok, scene_tok, lidar_tok = token("log", LOG), token("scene", LOG), token("lidar", LOG)

    # Sweep clock: frames at even sweeps, midpoints at odd ones.
    S = 2 * F - 1
    sweep_t = np.interp(np.arange(S) / 2.0, np.arange(F), src.times)  # (S,) seconds
    sweep_us = FIRST_US + np.round(sweep_t * 1e6).astype(np.int64)
    ego_gen = interpolate_poses(src.times, src.ego, sweep_t)  # (S, 4, 4) generator world
    ego_global = GLOBAL_FROM_GENERATOR[None] @ ego_gen

    def add_ego(tok: bytes, us: int, T: np.ndarray) -> None:
        q = rotmat_to_quat(T[:3, :3])
        rows["ego_pose"].append((tok, int(us), *map(float, T[:3, 3]), *map(float, q), *([0.0] * 9), 32611, log_tok))

    rows["log"].append((log_tok, "veh-99", "2021-06-07", int(FIRST_US), LOG, "synthetic", "synthetic-map"))
    rows["scene"].append((scene_tok, log_tok, f"scene-{LOG}", None, ""))
    rows["category"] = [(token("category", n), n, f"{n}.") for n in CATEGORIES]
    lidar_to_ego = rigid(LIDAR_TO_EGO_ROTATION, src.lidar_to_ego[:3, 3])
    rows["lidar"].append((lidar_tok, log_tok, "MergedPointCloud", "synthetic",
                          _pickle(lidar_to_ego[:3, 3]), _pickle(rotmat_to_quat(lidar_to_ego[:3, :3]))))

    # LiDAR sweeps: points of the frame at or before each sweep, in the sweep's sensor frame.
    beams = synthetic_beam_model(src)
    pc_tok = [token("lidar_pc", LOG, s) for s in range(S)]
    for s in range(S):
        f = s // 2
        ego_tok = token("ego_pose", "lidar_pc", LOG, s)
        add_ego(ego_tok, sweep_us[s], ego_global[s])
        rel = f"{LOG}/MergedPointCloud/{pc_tok[s].hex()}.pcd"
        rows["lidar_pc"].append((pc_tok[s], pc_tok[s + 1] if s + 1 < S else None, pc_tok[s - 1] if s else None,
                                 ego_tok, lidar_tok, scene_tok, rel, int(sweep_us[s])))
        sensor = ego_gen[s] @ lidar_to_ego
        local = (src.points(f) - sensor[:3, 3]) @ sensor[:3, :3]  # (N, 3) sensor frame
        inten = src.intensity[f] if src.intensity[f] is not None else np.zeros(len(local))
        rec = np.zeros(len(local), dtype=[(n, "<f4") for n in ("x", "y", "z", "intensity", "ring", "lidar_info")])
        rec["x"], rec["y"], rec["z"] = local.T
        rec["intensity"] = BYTE_INTENSITY.from_unit(inten)
        rec["ring"], rec["lidar_info"] = rings_and_lidars(src, f, beams)
        atomic_write_bytes(blobs_path(output) / rel, write_pcd(rec))

    # Cameras: one image per frame at the frame time, each with its own ego_pose row.
    for c, ch in enumerate(channels):
        cam = src.scene.cameras[c]
        cam_tok = token("camera", LOG, ch)
        K = src.K[c].copy()
        K[:2, 2] -= 0.5  # nuPlan K: pixel centres at integers
        T = src.cam_to_ego[c]
        rows["camera"].append((cam_tok, log_tok, ch, "synthetic", _pickle(T[:3, 3]), _pickle(rotmat_to_quat(T[:3, :3])),
                               _pickle(K), _pickle(np.zeros(5)), int(cam.width), int(cam.height)))
        img_tok = [token("image", LOG, ch, f) for f in range(F)]
        for f in range(F):
            ego_tok = token("ego_pose", "image", LOG, ch, f)
            add_ego(ego_tok, sweep_us[2 * f], ego_global[2 * f])
            rel = f"{LOG}/{ch}/{img_tok[f].hex()}.jpg"
            rows["image"].append((img_tok[f], img_tok[f + 1] if f + 1 < F else None, img_tok[f - 1] if f else None,
                                  ego_tok, cam_tok, rel, int(sweep_us[2 * f])))
            atomic_write_bytes(blobs_path(output) / rel, Path(cam.image_paths[f]).read_bytes())

    _boxes(src, rows, sweep_t, pc_tok)
    _write_database(database_path(output), rows)
    src.save_ground_truth(output, GLOBAL_FROM_GENERATOR, "nuPlan log layout; file_from_generator maps to the "
                          "nuPlan global frame; frame f is lidar_pc 2f")
    return {"frames": F, "sweeps": S, "channels": list(channels), "first_us": FIRST_US, "log": LOG}


def synthetic_beam_model(src: SyntheticSource) -> BeamModel:
    """The generator's LiDAR (``omnire synth`` options ``lidar_*``; its defaults where the
    ground truth does not list them): beams evenly spaced over the elevation range."""
    opts = src.meta.get("options", {})
    return BeamModel(np.linspace(*opts.get("lidar_elevation_deg", (-25.0, 10.0)), int(opts.get("lidar_beams", 32))),
                     float(opts.get("lidar_azimuth_step_deg", 0.4)), float(opts.get("lidar_max_range", 120.0)),
                     float(opts.get("lidar_min_range", 0.3)), "synthetic")


def rings_and_lidars(src: SyntheticSource, f: int, model: BeamModel) -> tuple[np.ndarray, np.ndarray]:
    """(N,) ring and (N,) lidar_info of frame ``f``'s returns: each return's beam (nearest
    elevation in the synthetic LiDAR's frame at ``f``, whose axes are the ego's) for the top
    LiDAR; in :data:`BACK_SECTOR_DEG` the back LiDAR, rings numbered from the top beam."""
    sensor = src.ego[f] @ src.lidar_to_ego
    _, az, el = spherical((src.points(f) - sensor[:3, 3]) @ sensor[:3, :3])
    beam = assign_beams(el, model).astype(np.int64)
    back = (az >= BACK_SECTOR_DEG[0]) & (az < BACK_SECTOR_DEG[1])
    ring = np.where(back, model.num_beams - 1 - beam, beam)
    return ring, np.where(back, BACK_LIDAR, 0)


def _boxes(src: SyntheticSource, rows: dict, sweep_t: np.ndarray, pc_tok: list[bytes]) -> None:
    """track and lidar_box rows of the actors present at each sweep."""
    cat_tok = {n: token("category", n) for n in CATEGORIES}
    for i, (tid, kind) in enumerate(zip(src.track_ids, src.kinds)):
        boxes = GLOBAL_FROM_GENERATOR[None] @ src.boxes[i]  # (F, 4, 4) box -> global
        poses, present = interpolate_track(src.times, boxes, src.present[i], sweep_t,
                                           max_gap=float(np.diff(src.times).max(initial=0.0)) * 1.001)
        sweeps = np.flatnonzero(present)
        if not len(sweeps):
            continue
        up = poses[sweeps, :3, 2]
        if np.abs(up[:, 2] - 1.0).max() > 1e-9:
            raise UserError(f"{src.source}: actor {tid} is rolled or pitched; nuPlan boxes hold a yaw only")
        l, w, h = (float(v) for v in src.sizes[i])
        track_tok = token("track", LOG, tid)
        rows["track"].append((track_tok, cat_tok[CATEGORY_OF_KIND[str(kind)]], w, l, h))
        toks = [token("lidar_box", LOG, tid, s) for s in sweeps]
        centres = poses[sweeps, :3, 3]
        velocity = np.gradient(centres, sweep_t[sweeps], axis=0) if len(sweeps) > 1 else np.zeros((1, 3))
        for j, s in enumerate(sweeps):
            R = poses[s, :3, :3]
            rows["lidar_box"].append((
                toks[j], pc_tok[s], track_tok, toks[j + 1] if j + 1 < len(toks) else None, toks[j - 1] if j else None,
                *map(float, centres[j]), w, l, h, *map(float, velocity[j]), float(np.arctan2(R[1, 0], R[0, 0])), 1.0,
            ))


def _pickle(values: np.ndarray) -> bytes:
    """A calibration cell: the pickled (nested) list of floats."""
    return pickle.dumps(np.asarray(values, dtype=np.float64).tolist(), protocol=2)


def _write_database(path: Path, rows: dict[str, list[tuple]]) -> None:
    """Build the SQLite file aside, then move it into place whole."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp_db = Path(tmp) / "log.db"
        conn = sqlite3.connect(tmp_db)
        try:
            for table, body in SCHEMA.items():
                conn.execute(f"CREATE TABLE {table} ({body}, PRIMARY KEY (token))")
                if rows[table]:
                    width = len(rows[table][0])
                    conn.executemany(f"INSERT INTO {table} VALUES ({','.join('?' * width)})", rows[table])
            conn.commit()
        finally:
            conn.close()
        atomic_write_bytes(path, tmp_db.read_bytes())
