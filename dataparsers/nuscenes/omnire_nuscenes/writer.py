"""Scene writer ``nuscenes``: a synthetic scene (``omnire synth``) in the nuScenes release
layout, so the reader is tested on scenes where every pose, box and point is known.

What is written (``<output>/``), as a nuScenes release has it (schema: nuscenes-devkit
``docs/schema_nuscenes.md``)::

    v1.0-mini/{attribute,calibrated_sensor,category,ego_pose,instance,log,map,sample,
               sample_annotation,sample_data,scene,sensor,visibility}.json
    samples/<CHANNEL>/<logfile>__<CHANNEL>__<timestamp>.jpg|.pcd.bin   keyframes
    sweeps/<CHANNEL>/<logfile>__<CHANNEL>__<timestamp>.jpg|.pcd.bin    other frames
    maps/<token>.png                                                  placeholder mask
    ground_truth.npz/.json    the generator's ground truth (not part of the layout)

- One LIDAR_TOP sweep and one image per camera per synthetic frame (the generator renders
  all sensors at the frame time: 10 Hz, synchronous; real nuScenes runs LiDAR at 20 Hz and
  cameras at 12 Hz). Keyframes (samples, annotated) every ``round(fps / 2)`` frames (2 Hz at
  10 fps), plus the last frame so no sweep trails the scene; the other frames are sweeps
  linked to the next sample, as in nuScenes.
- Timestamps: integer microseconds from a 2018 Unix time. Every sample_data has its own
  ego_pose (token = sample_data token, as in nuScenes), z = 0 and yaw only, in a global map
  frame = generator world rotated and shifted.
- Cameras: synthetic cameras 0..5 are CAM_FRONT, CAM_FRONT_LEFT, CAM_FRONT_RIGHT,
  CAM_BACK_LEFT, CAM_BACK_RIGHT, CAM_BACK; JPEG bytes copied unchanged; camera_intrinsic is
  omnire's K unchanged (nuScenes centres pixels at +0.5 as omnire does; docs/datasets.md).
- LIDAR_TOP: axes x right, y forward, z up on the car (plus a 0.2 degree mounting tilt), at
  the synthetic sensor's position; points float32 x y z intensity (0-255) ring (beam index).
- Annotations on keyframes: global centre, rotation (x along the heading), size (width,
  length, height), num_lidar_pts counted in the keyframe sweep, attributes from the motion.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from omnire.api import BYTE_INTENSITY, atomic_write_bytes, atomic_write_text, interpolate_poses, rigid, rotmat_to_quat
from omnire.api import axis_rotation as rot_axis
from omnire_nuscenes.dataparser import CAMERAS, LIDAR
from omnire_processed.groundtruth import SyntheticSource

VERSION = "v1.0-mini"
GLOBAL_FROM_GENERATOR = rigid(rot_axis(2, 0.7), (411.3, 1180.9, 0.0))
"""Generator world -> the written global (map) frame: a turn and a shift, z kept (ego z = 0)."""
LIDAR_AXES = rot_axis(2, -np.pi / 2) @ rot_axis(0, np.deg2rad(0.2))
"""LIDAR_TOP axes in the ego frame: x right, y forward, z up, slightly tilted."""
FIRST_US = 1532402927647951
LOGFILE = "n000-2018-07-24-11-22-45+0800"
CLASS_OF_KIND = {"car": "vehicle.car", "pedestrian": "human.pedestrian.adult", "cyclist": "vehicle.bicycle"}
CATEGORIES = (
    "animal", "human.pedestrian.adult", "human.pedestrian.child", "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility", "human.pedestrian.police_officer", "human.pedestrian.stroller",
    "human.pedestrian.wheelchair", "movable_object.barrier", "movable_object.debris",
    "movable_object.pushable_pullable", "movable_object.trafficcone", "static_object.bicycle_rack",
    "vehicle.bicycle", "vehicle.bus.bendy", "vehicle.bus.rigid", "vehicle.car", "vehicle.construction",
    "vehicle.emergency.ambulance", "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer",
    "vehicle.truck",
)
"""The 23 annotated nuScenes classes."""
ATTRIBUTES = ("vehicle.moving", "vehicle.stopped", "vehicle.parked", "cycle.with_rider", "cycle.without_rider",
              "pedestrian.sitting_lying_down", "pedestrian.standing", "pedestrian.moving")
VISIBILITY = (("1", "v0-40"), ("2", "v40-60"), ("3", "v60-80"), ("4", "v80-100"))


def token(*parts) -> str:
    """A deterministic 32-hex-digit token (nuScenes tokens have that form)."""
    return hashlib.md5(":".join(map(str, parts)).encode()).hexdigest()


def write_scene(source: Path, output: Path) -> None:
    """Scene-writer entry point (``omnire synth --format nuscenes``)."""
    write_nuscenes(source, output)


def write_nuscenes(source: Path, output: Path, camera_delays: Optional[Sequence[float]] = None) -> dict:
    """Write the synthetic scene in ``source`` into the empty folder ``output`` (layout in
    the module docstring). ``camera_delays`` (seconds per camera, default 0) shifts each
    camera's timestamps and ego poses from the frame time, to test readers on asynchronous
    cameras; the images stay those rendered at the frame time. Returns a summary."""
    src = SyntheticSource.load(Path(source))
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    F, C = src.num_frames, len(src.scene.cameras)
    if C > len(CAMERAS):
        raise ValueError(f"{source}: {C} cameras; nuScenes has {len(CAMERAS)}")
    channels = CAMERAS[:C]
    delays = np.zeros(C) if camera_delays is None else np.asarray(camera_delays, dtype=np.float64)
    fps = float(src.meta.get("fps", 10.0))
    every = max(1, round(fps / 2.0))
    keyframes = sorted(set(range(0, F, every)) | {F - 1})
    frame_us = FIRST_US + np.round(src.times * 1e6).astype(np.int64)
    ego_global = GLOBAL_FROM_GENERATOR[None] @ src.ego  # (F, 4, 4)

    log_tok, scene_tok = token("log", LOGFILE), token("scene", LOGFILE)
    sample_tok = {f: token("sample", LOGFILE, f) for f in keyframes}
    tables: dict[str, list[dict]] = {k: [] for k in (
        "attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
        "sample_annotation", "sample_data", "scene", "sensor", "visibility")}
    tables["log"].append({"token": log_tok, "logfile": LOGFILE, "vehicle": LOGFILE.split("-")[0],
                          "date_captured": "2018-07-24", "location": f"synthetic-{src.meta.get('preset', 'scene')}"})
    tables["scene"].append({
        "token": scene_tok, "log_token": log_tok, "nbr_samples": len(keyframes),
        "first_sample_token": sample_tok[keyframes[0]], "last_sample_token": sample_tok[keyframes[-1]],
        "name": "scene-0001",
        "description": f"omnire synthetic {src.meta.get('preset')} scene, seed {src.meta.get('seed')}, {F} frames",
    })
    for i, f in enumerate(keyframes):
        tables["sample"].append({
            "token": sample_tok[f], "timestamp": int(frame_us[f]), "scene_token": scene_tok,
            "prev": sample_tok[keyframes[i - 1]] if i else "",
            "next": sample_tok[keyframes[i + 1]] if i + 1 < len(keyframes) else "",
        })
    next_sample = {f: sample_tok[min(k for k in keyframes if k >= f)] for f in range(F)}

    # Sensors and their calibration (one calibrated_sensor per sensor, as for one log).
    lidar_to_ego = rigid(LIDAR_AXES, src.lidar_to_ego[:3, 3])
    sensors = [(LIDAR, "lidar", lidar_to_ego, [])]
    for c, ch in enumerate(channels):
        sensors.append((ch, "camera", src.cam_to_ego[c], src.K[c].tolist()))
    calib_tok = {}
    for ch, modality, T, K in sensors:
        sen_tok, calib_tok[ch] = token("sensor", ch), token("calibrated_sensor", LOGFILE, ch)
        tables["sensor"].append({"token": sen_tok, "channel": ch, "modality": modality})
        tables["calibrated_sensor"].append({
            "token": calib_tok[ch], "sensor_token": sen_tok, "translation": T[:3, 3].tolist(),
            "rotation": rotmat_to_quat(np.asarray(T[:3, :3], dtype=np.float64)).tolist(), "camera_intrinsic": K,
        })

    def add_sample_data(ch: str, f: int, us: int, pose: np.ndarray, ext: str, fmt: str, w: int, h: int,
                        prev: str) -> tuple[str, str]:
        key = f in sample_tok
        sd_tok = token("sample_data", LOGFILE, ch, f)
        rel = f"{'samples' if key else 'sweeps'}/{ch}/{LOGFILE}__{ch}__{us}{ext}"
        tables["ego_pose"].append({"token": sd_tok, "timestamp": us, "rotation": rotmat_to_quat(pose[:3, :3]).tolist(),
                                   "translation": pose[:3, 3].tolist()})
        tables["sample_data"].append({
            "token": sd_tok, "sample_token": next_sample[f], "ego_pose_token": sd_tok,
            "calibrated_sensor_token": calib_tok[ch], "timestamp": us, "fileformat": fmt, "is_key_frame": key,
            "height": h, "width": w, "filename": rel, "prev": prev, "next": "",
        })
        if prev:  # frames of one channel are added in a row: the previous record is the one before
            tables["sample_data"][-2]["next"] = sd_tok
        return sd_tok, rel

    # LIDAR_TOP sweeps: points of the processed scene re-expressed in the LiDAR frame.
    opts = src.meta.get("options", {})
    elev_lo, elev_hi = np.deg2rad(opts.get("lidar_elevation_deg", (-25.0, 10.0)))
    beams = int(opts.get("lidar_beams", 32))
    prev = ""
    key_points = {}
    for f in range(F):
        pose = ego_global[f]
        prev, rel = add_sample_data(LIDAR, f, int(frame_us[f]), pose, ".pcd.bin", "pcd", 0, 0, prev)
        p_gen = src.points(f)
        if f in sample_tok:
            key_points[f] = p_gen
        sensor_gen = src.ego[f] @ lidar_to_ego
        local = (p_gen - sensor_gen[:3, 3]) @ sensor_gen[:3, :3]  # (N, 3) LiDAR frame
        level = (p_gen - sensor_gen[:3, 3]) @ src.ego[f][:3, :3]  # ego-aligned axes: beam elevation
        elev = np.arctan2(level[:, 2], np.hypot(level[:, 0], level[:, 1]))
        ring = np.clip(np.round((elev - elev_lo) / max(elev_hi - elev_lo, 1e-9) * (beams - 1)), 0, beams - 1)
        inten = src.intensity[f] if src.intensity[f] is not None else np.zeros(len(local))
        rows = np.column_stack([local, BYTE_INTENSITY.from_unit(inten), ring]).astype("<f4")
        atomic_write_bytes(output / rel, rows.tobytes())

    # Cameras: one image per frame, JPEG bytes unchanged.
    for c, ch in enumerate(channels):
        cam = src.scene.cameras[c]
        prev = ""
        for f in range(F):
            t = src.times[f] + delays[c]
            pose = GLOBAL_FROM_GENERATOR @ (src.ego[f] if delays[c] == 0 else interpolate_poses(src.times, src.ego, t)[0])
            us = int(FIRST_US + round(t * 1e6))
            prev, rel = add_sample_data(ch, f, us, pose, ".jpg", "jpg", cam.width, cam.height, prev)
            atomic_write_bytes(output / rel, Path(cam.image_paths[f]).read_bytes())

    _annotations(src, tables, keyframes, sample_tok, key_points)
    tables["attribute"] = [{"token": token("attribute", a), "name": a, "description": a.replace(".", " ")}
                           for a in ATTRIBUTES]
    tables["visibility"] = [{"token": t, "level": lvl, "description": f"visibility of whole object is {lvl[1:]}%"}
                            for t, lvl in VISIBILITY]
    tables["category"] = [{"token": token("category", n), "name": n, "description": n.replace(".", " ")}
                          for n in CATEGORIES]
    map_tok = token("map", LOGFILE)
    tables["map"] = [{"token": map_tok, "log_tokens": [log_tok], "category": "semantic_prior",
                      "filename": f"maps/{map_tok}.png"}]
    _write_placeholder_map(output / "maps" / f"{map_tok}.png")
    for name, records in tables.items():
        atomic_write_text(output / VERSION / f"{name}.json", json.dumps(records, indent=0))
    src.save_ground_truth(output, GLOBAL_FROM_GENERATOR,
                          f"nuScenes layout ({VERSION}); file_from_generator maps to the nuScenes global frame")
    return {"frames": F, "keyframes": keyframes, "channels": list(channels), "first_us": FIRST_US}


def _annotations(src: SyntheticSource, tables: dict, keyframes: list[int], sample_tok: dict, key_points: dict) -> None:
    """sample_annotation and instance records of the actors present on keyframes."""
    attr_tok = {a: token("attribute", a) for a in ATTRIBUTES}
    for i, (tid, kind) in enumerate(zip(src.track_ids, src.kinds)):
        frames = [f for f in keyframes if src.present[i, f]]
        if not frames:
            continue
        inst_tok = token("instance", LOGFILE, tid)
        toks = [token("sample_annotation", LOGFILE, tid, f) for f in frames]
        l, w, h = (float(v) for v in src.sizes[i])
        for j, f in enumerate(frames):
            box = src.boxes[i, f]
            local = (key_points[f] - box[:3, 3]) @ box[:3, :3]
            n_pts = int((np.abs(local) <= src.sizes[i] / 2).all(axis=1).sum())
            G = GLOBAL_FROM_GENERATOR @ box
            tables["sample_annotation"].append({
                "token": toks[j], "sample_token": sample_tok[f], "instance_token": inst_tok,
                "visibility_token": "4", "attribute_tokens": [attr_tok[_attribute(src, i, f, kind)]],
                "translation": G[:3, 3].tolist(), "size": [w, l, h], "rotation": rotmat_to_quat(G[:3, :3]).tolist(),
                "prev": toks[j - 1] if j else "", "next": toks[j + 1] if j + 1 < len(toks) else "",
                "num_lidar_pts": n_pts, "num_radar_pts": 0,
            })
        tables["instance"].append({"token": inst_tok, "category_token": token("category", CLASS_OF_KIND[str(kind)]),
                                   "nbr_annotations": len(frames), "first_annotation_token": toks[0],
                                   "last_annotation_token": toks[-1]})


def _attribute(src: SyntheticSource, i: int, f: int, kind: str) -> str:
    """nuScenes attribute from the actor's speed around frame ``f``."""
    F = src.num_frames
    a, b = max(f - 1, 0), min(f + 1, F - 1)
    while a < f and not src.present[i, a]:
        a += 1
    while b > f and not src.present[i, b]:
        b -= 1
    speed = 0.0 if b == a else np.linalg.norm(src.boxes[i, b, :3, 3] - src.boxes[i, a, :3, 3]) / (src.times[b] - src.times[a])
    if kind == "cyclist":
        return "cycle.with_rider"
    if kind == "pedestrian":
        return "pedestrian.moving" if speed > 0.3 else "pedestrian.standing"
    if speed > 0.5:
        return "vehicle.moving"
    return "vehicle.parked" if src.stationary[i] else "vehicle.stopped"


def _write_placeholder_map(path: Path) -> None:
    """A small all-zero semantic-prior mask (the real map rasters are not synthesised)."""
    import OpenImageIO as oiio

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None or not out.open(str(tmp), oiio.ImageSpec(8, 8, 1, "uint8")) or not out.write_image(
            np.zeros((8, 8, 1), np.uint8)):
        raise OSError(f"{tmp}: cannot write the placeholder map ({oiio.geterror()})")
    out.close()
    shutil.move(str(tmp), str(path))
