"""nuScenes reader: one scene of a nuScenes release, read in place -> :class:`SceneData`.

Layout read (``--data`` is the data root; ``--version`` names the table folder)::

    <data>/v1.0-mini/{scene,sample,sample_data,ego_pose,calibrated_sensor,sensor,
                      sample_annotation,instance,category,log}.json
    <data>/samples/<CHANNEL>/<logfile>__<CHANNEL>__<timestamp>.{jpg,pcd.bin}   keyframes
    <data>/sweeps/<CHANNEL>/<logfile>__<CHANNEL>__<timestamp>.{jpg,pcd.bin}    in between

Facts used (nuscenes-devkit ``docs/schema_nuscenes.md`` and ``utils/data_classes.py``):

- Timestamps are integer microseconds (Unix time). Every ``sample_data`` (one image or one
  LiDAR sweep) has its own ``ego_pose`` (ego-to-global at that timestamp; the localisation
  is 2-D, z = 0) and ``calibrated_sensor`` (sensor-to-ego). Quaternions are w, x, y, z.
- Cameras: the calibrated camera frame is OpenCV's (x right, y down, z forward), so
  cam_to_world = world @ ego_pose(image) @ calibrated_sensor(camera). "All camera images come
  undistorted and rectified": no distortion coefficients. ``camera_intrinsic`` is a 3x3 K.
  The schema does not state the pixel origin; the devkit's geometry treats the image as the
  rectangle [0, W] x [0, H] (``box_in_image`` keeps 0 < u < W, ``map_pointcloud_to_image``
  keeps a 1 px margin on each side, the 2D-box export clips to ``box(0, 0, 1600, 900)``),
  which centres pixel (i, j) at (i + 0.5, j + 0.5), omnire's convention: K is used as is
  (the processed reader reads the reference's copy of the same K the same way; see
  docs/datasets.md, nuScenes).
- LIDAR_TOP ``.pcd.bin``: float32 rows x y z intensity ring, in the LiDAR frame (x right,
  y forward, z up on the car; its calibrated_sensor says so). Intensity (0-255) / 255 and
  ring (the beam, :data:`HDL32E`) ride along; ``sensor_to_world`` is that frame in x-forward
  axes at the sweep's timestamp. The files hold no per-point time (``times`` is None).
- Boxes (``sample_annotation``, keyframes only, 2 Hz): centre and rotation in the global
  frame; ``size`` is (width, length, height) and the box's x axis runs along the length
  (devkit ``Box.corners``: x forward, y left, z up). omnire boxes keep that rotation (x along
  the heading) with size = (length, width, height) = (size[1], size[0], size[2]).

Frames follow the reference implementation's 10 Hz choice: between two consecutive keyframes
``interpolate_frames`` target times are spaced evenly, and each target (keyframes included)
takes the LIDAR_TOP sweep nearest in time (the same sweep twice is kept once). The frame
clock is those sweeps' timestamps; each camera takes, per frame, its image nearest in time
and keeps that image's exact timestamp and ego pose. Boxes are interpolated (SLERP + linear,
``omnire.api.interpolate_track``) from the keyframe annotations to the sweep timestamps, at
the times of the keyframe LiDAR sweeps they were annotated on.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional, Type

import numpy as np

from omnire.api import (
    BYTE_INTENSITY, ActorTrack, BeamModel, CameraSequence, ConfigError, Dataparser, LidarSweeps, LogDataparserConfig,
    MaxTrackGap, SceneData, first_pose_world, frame_range, image_size, is_stationary, loaded_camera, nearest_index,
    resample_track, thin_points,
)
from omnire_nuscenes.tables import (
    NuScenesDataError,
    NuScenesFileMissing,
    load_table,
    lookup,
    number_array,
    pose_matrix,
)

CAMERAS = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK_RIGHT", "CAM_BACK")
"""The six nuScenes cameras (the reference's camera ids 0..5 in this order)."""
LIDAR = "LIDAR_TOP"
LIDAR_COLUMNS = 5
"""float32 values per point in a ``.pcd.bin``: x, y, z, intensity (0-255), ring index."""
HDL32E = BeamModel(np.linspace(-30.67, 10.67, 32), azimuth_resolution_deg=1.0 / 3.0, max_range=70.0, min_range=0.0,
                   name="Velodyne HDL-32E")
"""LIDAR_TOP: 32 lasers evenly spread over +10.67 to -30.67 degrees (Velodyne HDL-32E
datasheet), ring index r = the r-th lowest laser (the ring numbering of Velodyne's ROS
driver, ascending elevation); 20 Hz with 1080 points per ring (0.33 degrees) and a range up
to 70 m (nuScenes' sensor description)."""
FORWARD_IN_LIDAR = np.array([[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""(4, 4) x-forward sensor axes -> LIDAR_TOP axes (x right, y forward, z up): its columns
are forward, left and up in LIDAR_TOP coordinates."""

ATTRIBUTION = (
    '"nuScenes: A multimodal dataset for autonomous driving", Caesar et al., CVPR 2020; nuScenes by Motional, '
    "CC BY-NC-SA 4.0 (non-commercial use; nuScenes Terms of Use)."
)


def category_of(name: str) -> str:
    """nuScenes category name -> omnire actor category (vehicle, human, cyclist, other)."""
    if name.startswith(("vehicle.bicycle", "vehicle.motorcycle", "human.pedestrian.personal_mobility")):
        return "cyclist"  # two-wheelers with riders and scooters/skateboards: non-rigid
    if name.startswith(("human.pedestrian.stroller", "human.pedestrian.wheelchair")):
        return "other"  # not a walking body: no SMPL pose fits
    if name.startswith("human.pedestrian"):
        return "human"
    if name.startswith("vehicle."):
        return "vehicle"
    return "other"  # animal, movable_object.*, static_object.*


def frame_targets(keyframe_times: np.ndarray, between: int) -> np.ndarray:
    """Target times (int64 microseconds): each keyframe plus ``between`` evenly spaced times
    in every interval between consecutive keyframes (the reference's interpolated mode)."""
    k = np.asarray(keyframe_times, dtype=np.int64)
    out = []
    for a, b in zip(k[:-1], k[1:]):
        out.extend(int(a + j * (b - a) / (between + 1)) for j in range(between + 1))
    out.append(int(k[-1]))
    return np.asarray(out, dtype=np.int64)


class NuScenesDataparser(Dataparser):
    """Reads one nuScenes scene (see the module docstring for the layout and conventions)."""

    config: "NuScenesConfig"

    def parse(self) -> SceneData:
        cfg = self.config
        self._check_options()
        root, tables = self._locate()
        scene = self._scene(tables)
        samples = self._samples(tables, scene)  # ordered keyframes
        sample_tokens = {s["token"] for s in samples}
        sds = load_table(tables, "sample_data", keep=lambda r: r["sample_token"] in sample_tokens)
        calib_tokens = {r["calibrated_sensor_token"] for r in sds}
        calibs = {r["token"]: r for r in load_table(tables, "calibrated_sensor",
                                                      keep=lambda r: r["token"] in calib_tokens)}
        sensors = {r["token"]: r for r in load_table(tables, "sensor")}
        by_channel: dict[str, list[dict]] = {}
        for r in sds:
            cal = lookup(calibs, r["calibrated_sensor_token"], "calibrated_sensor", tables,
                         f"sample_data {r['token']!r} field 'calibrated_sensor_token'")
            sen = lookup(sensors, cal["sensor_token"], "sensor", tables,
                         f"calibrated_sensor {cal['token']!r} field 'sensor_token'")
            by_channel.setdefault(str(sen["channel"]), []).append(r)
        for recs in by_channel.values():
            recs.sort(key=lambda r: int(r["timestamp"]))
        cameras = self._camera_names(by_channel, tables)

        # Frame clock: LIDAR_TOP sweeps nearest the reference's evenly spaced targets.
        lidar_sds = by_channel.get(LIDAR)
        if not lidar_sds:
            raise NuScenesDataError(f"{tables / 'sample_data.json'}: scene {scene['name']!r} has no {LIDAR} "
                                    "sample_data (the frame clock of this reader)")
        lidar_t = np.array([int(r["timestamp"]) for r in lidar_sds], dtype=np.int64)
        key_sweep = {r["sample_token"]: r for r in lidar_sds if bool(r["is_key_frame"])}
        # Annotations belong to the keyframe sweep of their sample (sample.timestamp as fallback).
        key_t = np.array([int(key_sweep[s["token"]]["timestamp"]) if s["token"] in key_sweep else int(s["timestamp"])
                          for s in samples], dtype=np.int64)
        if np.any(np.diff(key_t) <= 0):
            raise NuScenesDataError(f"{tables / 'sample.json'}: keyframes of scene {scene['name']!r} are not in "
                                    "increasing time order along their 'next' links")
        chosen = nearest_index(lidar_t.astype(np.float64), frame_targets(key_t, cfg.interpolate_frames).astype(np.float64))
        chosen = chosen[np.concatenate([[True], np.diff(chosen) != 0])]  # same sweep twice: once
        rng = frame_range(cfg.start_frame, cfg.end_frame, len(chosen), f"nuScenes scene {scene['name']!r}")
        frame_sds = [lidar_sds[i] for i in chosen[rng.start:rng.stop]]
        frame_us = np.array([int(r["timestamp"]) for r in frame_sds], dtype=np.int64)

        cam_sds = {}
        for name in cameras:
            recs = by_channel[name]
            t = np.array([int(r["timestamp"]) for r in recs], dtype=np.float64)
            cam_sds[name] = [recs[i] for i in nearest_index(t, frame_us.astype(np.float64))]
        ego_tokens = {r["ego_pose_token"] for r in frame_sds} | {r["ego_pose_token"] for v in cam_sds.values() for r in v}
        ego = {r["token"]: r for r in load_table(tables, "ego_pose", keep=lambda r: r["token"] in ego_tokens)}

        def ego_of(sd: dict) -> np.ndarray:
            rec = lookup(ego, sd["ego_pose_token"], "ego_pose", tables, f"sample_data {sd['token']!r} field 'ego_pose_token'")
            return pose_matrix(rec, "ego_pose", tables)

        def calib_of(sd: dict) -> np.ndarray:
            return pose_matrix(calibs[sd["calibrated_sensor_token"]], "calibrated_sensor", tables)

        ego_frames = np.stack([ego_of(r) for r in frame_sds])  # (F, 4, 4) ego -> global
        world = first_pose_world(ego_frames[0])  # (4, 4) global -> omnire world
        cams = [self._camera(root, tables, name, cam_sds[name], calibs, ego_of, calib_of, world) for name in cameras]
        lidar = self._lidar(root, frame_sds, ego_frames, calib_of, world) if cfg.load_lidar else None
        tracks = self._tracks(tables, samples, key_t, frame_us, world)
        return self.build_scene(f"nuscenes_{scene['name']}", cams, frame_us * 1e-6, np.arange(rng.start, rng.stop),
                                lidar=lidar, tracks=tracks, ego_poses=world[None] @ ego_frames, attribution=ATTRIBUTION)

    # -- options and tables -------------------------------------------------------------------
    def _check_options(self) -> None:
        cfg = self.config
        cfg.check()
        if cfg.interpolate_frames < 0:
            raise ConfigError(f"interpolate_frames: {cfg.interpolate_frames}, expected >= 0 (0 = keyframes only)")
        bad = [c for c in cfg.cameras if c not in CAMERAS]
        if bad:
            raise ConfigError(f"cameras: {bad} are not nuScenes cameras; choose from {list(CAMERAS)}")

    def _locate(self) -> tuple[Path, Path]:
        """(data root holding samples/ and sweeps/, folder of the JSON tables)."""
        data = Path(self.config.data)
        if not data.is_dir():
            raise NuScenesFileMissing(
                f"{data}: nuScenes data root does not exist; expected the folder holding samples/, sweeps/ and "
                f"the table folder {self.config.version}/"
            )
        if (data / "scene.json").is_file():  # --data points at the table folder itself
            return data.parent, data
        tables = data / self.config.version
        if not tables.is_dir():
            found = sorted(p.name for p in data.iterdir() if p.is_dir() and (p / "scene.json").is_file())
            raise NuScenesFileMissing(f"{tables}: no such table folder (--version {self.config.version}); "
                                      f"table folders in {data}: {found or 'none'}")
        return data, tables

    def _scene(self, tables: Path) -> dict:
        scenes = load_table(tables, "scene")
        want = self.config.scene
        if not want:
            if len(scenes) == 1:
                return scenes[0]
            names = [s["name"] for s in scenes]
            more = f" and {len(names) - 12} more" if len(names) > 12 else ""
            raise ConfigError(f"scene: empty, but {tables / 'scene.json'} holds {len(names)} scenes; choose one by "
                              f"name or token with --scene (e.g. {', '.join(names[:12])}{more})")
        hits = [s for s in scenes if want in (s["name"], s["token"])]
        if not hits:
            names = [s["name"] for s in scenes][:12]
            raise ConfigError(f"scene: {want!r} is neither the name nor the token of a scene in "
                              f"{tables / 'scene.json'} (scenes: {', '.join(names)}{' ...' if len(scenes) > 12 else ''})")
        return hits[0]

    def _samples(self, tables: Path, scene: dict) -> list[dict]:
        """The scene's keyframes in order, following ``next`` from ``first_sample_token``."""
        recs = {r["token"]: r for r in load_table(tables, "sample", keep=lambda r: r["scene_token"] == scene["token"])}
        path = tables / "sample.json"
        out, token = [], scene["first_sample_token"]
        while True:
            rec = recs.get(token)
            if rec is None:
                where = ("scene.json field 'first_sample_token'" if not out
                         else f"sample {out[-1]['token']!r} field 'next'")
                raise NuScenesDataError(f"{path}: no sample {token!r} of scene {scene['name']!r} (referenced by {where})")
            out.append(rec)
            if token == scene["last_sample_token"]:
                break
            token = rec["next"]
            if not token or len(out) > len(recs):
                raise NuScenesDataError(f"{path}: the 'next' links from the first sample of scene {scene['name']!r} "
                                        f"do not reach its last_sample_token {scene['last_sample_token']!r}")
        if int(scene["nbr_samples"]) != len(out):
            raise NuScenesDataError(f"{tables / 'scene.json'}: scene {scene['name']!r} field 'nbr_samples' = "
                                    f"{scene['nbr_samples']}, but its sample chain has {len(out)} samples")
        return out

    def _camera_names(self, by_channel: dict[str, list[dict]], tables: Path) -> list[str]:
        present = [c for c in CAMERAS if c in by_channel]
        if not self.config.cameras:
            if not present:
                raise NuScenesDataError(f"{tables / 'sample_data.json'}: this scene has no camera sample_data "
                                        f"(channels: {sorted(by_channel)})")
            return present
        missing = [c for c in self.config.cameras if c not in by_channel]
        if missing:
            raise NuScenesDataError(f"cameras: {missing} have no sample_data in this scene; cameras present: {present}")
        return list(self.config.cameras)

    # -- sensors ---------------------------------------------------------------------------------
    def _camera(self, root: Path, tables: Path, name: str, sds: list[dict], calibs: dict, ego_of, calib_of,
                world: np.ndarray) -> CameraSequence:
        cal_tokens = sorted({r["calibrated_sensor_token"] for r in sds})
        Ks = [number_array(calibs[t], "camera_intrinsic", (3, 3), "calibrated_sensor", tables) for t in cal_tokens]
        if any(not np.allclose(K, Ks[0], rtol=0, atol=1e-9) for K in Ks):
            raise NuScenesDataError(f"{tables / 'calibrated_sensor.json'}: {name} changes its camera_intrinsic within "
                                    f"the loaded frames (records {cal_tokens}); one K per camera is supported")
        K0 = Ks[0]
        if K0[2, 2] != 1 or K0[1, 0] != 0 or K0[2, 0] != 0 or K0[2, 1] != 0 or K0[0, 0] <= 0 or K0[1, 1] <= 0:
            raise NuScenesDataError(f"{tables / 'calibrated_sensor.json'}: record {cal_tokens[0]!r} field "
                                    f"'camera_intrinsic' = {K0.tolist()} is not a pinhole K [[fx,s,cx],[0,fy,cy],[0,0,1]]")
        paths = [root / str(r["filename"]) for r in sds]
        missing = [(p, r) for p, r in zip(paths, sds) if not p.is_file()]
        if missing:
            p, r = missing[0]
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise NuScenesFileMissing(f"{p}: missing image of {name} (sample_data {r['token']!r} field 'filename'){more}")
        width, height = int(sds[0]["width"]), int(sds[0]["height"])
        w_disk, h_disk = image_size(paths[0])
        if (w_disk, h_disk) != (width, height):
            raise NuScenesDataError(f"{paths[0]}: image is {w_disk}x{h_disk}, but sample_data {sds[0]['token']!r} "
                                    f"fields 'width', 'height' say {width}x{height}")
        c2w = np.stack([world @ ego_of(r) @ calib_of(r) for r in sds])  # (F, 4, 4) OpenCV cam -> world
        extras = {"sample_data_token": np.array([str(r["token"]) for r in sds]),
                  "is_key_frame": np.array([bool(r["is_key_frame"]) for r in sds])}
        # Pixel centres at +0.5 already (module docstring): K is only scaled.
        return loaded_camera(name, paths, K0, (width, height), self.config.scale, "half", cam_to_world=c2w,
                             timestamps=np.array([int(r["timestamp"]) for r in sds], dtype=np.int64) * 1e-6,
                             distortion=None,  # nuScenes images are undistorted (schema: calibrated_sensor)
                             ego_mask_path=self._ego_mask(name), extras=extras)

    def _ego_mask(self, name: str) -> Optional[Path]:
        folder = self.config.ego_mask_dir
        if folder is None:
            return None
        if not Path(folder).is_dir():
            raise NuScenesFileMissing(f"{folder}: ego_mask_dir does not exist; expected a folder of <CHANNEL>.png masks")
        path = Path(folder) / f"{name}.png"
        return path if path.is_file() else None

    def _lidar(self, root: Path, sds: list[dict], ego_frames: np.ndarray, calib_of, world: np.ndarray) -> LidarSweeps:
        cfg = self.config
        points: list[Optional[np.ndarray]] = []
        intensity: list[Optional[np.ndarray]] = []
        beams: list[Optional[np.ndarray]] = []
        sensor_to_world = np.full((len(sds), 4, 4), np.nan)
        row = 4 * LIDAR_COLUMNS
        for j, sd in enumerate(sds):
            path = root / str(sd["filename"])
            if not path.is_file():  # a sweep not downloaded: a gap (keyframe-only copies lack sweeps/)
                points.append(None)
                intensity.append(None)
                beams.append(None)
                continue
            size = path.stat().st_size
            if size % row:
                raise NuScenesDataError(f"{path}: {size} bytes is not a whole number of {row}-byte points "
                                        f"({LIDAR_COLUMNS} float32: x y z intensity ring) (sample_data {sd['token']!r})")
            rows = np.fromfile(path, dtype="<f4").reshape(-1, LIDAR_COLUMNS).astype(np.float64)  # (N, 5) LiDAR frame
            if not np.isfinite(rows).all():
                raise NuScenesDataError(f"{path}: non-finite values (sample_data {sd['token']!r})")
            ring = rows[:, 4]
            if len(ring) and (ring.min() < 0 or ring.max() > HDL32E.num_beams - 1 or (ring != np.round(ring)).any()):
                raise NuScenesDataError(f"{path}: column 5 (ring) must hold whole numbers 0..{HDL32E.num_beams - 1} "
                                        f"(the HDL-32E's lasers) (sample_data {sd['token']!r})")
            rows[:, 3] = BYTE_INTENSITY.to_unit(rows[:, 3], f"{path}: column 4 (intensity)", NuScenesDataError)
            if cfg.lidar_min_distance > 0:
                rows = rows[np.hypot(rows[:, 0], rows[:, 1]) >= cfg.lidar_min_distance]
            rows = thin_points(rows, cfg.max_lidar_points_per_frame, sd["timestamp"])  # keyed by the sweep
            M = world @ ego_frames[j] @ calib_of(sd)  # (4, 4) LiDAR -> world
            points.append((rows[:, :3] @ M[:3, :3].T + M[:3, 3]).astype(np.float32))
            intensity.append(rows[:, 3].astype(np.float32))
            beams.append(rows[:, 4].astype(np.int16))
            sensor_to_world[j] = M @ FORWARD_IN_LIDAR
        if all(p is None for p in points):
            raise NuScenesFileMissing(f"{root / str(sds[0]['filename'])}: none of the {len(sds)} LiDAR files of the "
                                      "loaded frames exists (is --data the nuScenes data root?); --no-load-lidar skips LiDAR")
        return LidarSweeps(points=points, origins=sensor_to_world[:, :3, 3].copy(), intensity=intensity, beams=beams,
                           sensor_to_world=sensor_to_world, beam_model=HDL32E)

    def _tracks(self, tables: Path, samples: list[dict], key_t: np.ndarray, frame_us: np.ndarray,
                world: np.ndarray) -> list[ActorTrack]:
        cfg = self.config
        time_of = {s["token"]: int(t) for s, t in zip(samples, key_t)}
        anns = load_table(tables, "sample_annotation", keep=lambda r: r["sample_token"] in time_of)
        inst_tokens = {a["instance_token"] for a in anns}
        instances = {r["token"]: r for r in load_table(tables, "instance", keep=lambda r: r["token"] in inst_tokens)}
        categories = {r["token"]: r for r in load_table(tables, "category")}
        groups: dict[str, list[dict]] = {}
        for a in anns:
            groups.setdefault(a["instance_token"], []).append(a)
        tracks = []
        for inst_token, rows in sorted(groups.items()):
            inst = lookup(instances, inst_token, "instance", tables,
                          f"sample_annotation {rows[0]['token']!r} field 'instance_token'")
            cat = lookup(categories, inst["category_token"], "category", tables,
                         f"instance {inst_token!r} field 'category_token'")
            rows.sort(key=lambda a: time_of[a["sample_token"]])
            t = np.array([time_of[a["sample_token"]] for a in rows], dtype=np.float64)
            if np.any(np.diff(t) <= 0):
                raise NuScenesDataError(f"{tables / 'sample_annotation.json'}: instance {inst_token!r} is annotated "
                                        "twice in one sample")
            boxes = np.stack([pose_matrix(a, "sample_annotation", tables) for a in rows])  # (K, 4, 4) box -> global
            wlh = np.stack([number_array(a, "size", (3,), "sample_annotation", tables) for a in rows])  # (K, 3)
            if (wlh <= 0).any():
                raise NuScenesDataError(f"{tables / 'sample_annotation.json'}: instance {inst_token!r} has a box 'size' "
                                        "with a non-positive entry; expected width, length, height in metres")
            boxes = world[None] @ boxes
            poses, present = resample_track(t, boxes, frame_us.astype(np.float64), cfg.max_track_gap * 1e6)
            if not present.any():
                continue
            name = str(cat["name"])
            size = wlh[:, [1, 0, 2]].max(axis=0)  # (width, length, height) -> (length, width, height)
            stationary = is_stationary(poses[present, :3, 3], cfg.stationary_threshold)
            tracks.append(ActorTrack(inst_token, name, category_of(name), poses, size, present, stationary, extras={
                "annotation_times": t * 1e-6, "annotation_poses": boxes,
                "annotation_tokens": [a["token"] for a in rows]}))
        return tracks



@dataclasses.dataclass
class NuScenesConfig(LogDataparserConfig):
    """One scene of a nuScenes release (v1.0-mini / trainval / test tables, samples/ and sweeps/)."""

    _target: Type = dataclasses.field(default_factory=lambda: NuScenesDataparser)
    data: Path = Path("data/nuscenes")
    """nuScenes data root (holds samples/, sweeps/ and the table folder such as v1.0-mini/), or the table folder itself."""
    version: str = "v1.0-mini"
    """Table folder under --data: v1.0-mini, v1.0-trainval or v1.0-test."""
    scene: str = ""
    """Scene to load, by name (e.g. scene-0061) or token; empty loads the only scene of the tables."""
    cameras: tuple[str, ...] = ()
    """Cameras to load: any of CAM_FRONT, CAM_FRONT_LEFT, CAM_FRONT_RIGHT, CAM_BACK_LEFT, CAM_BACK_RIGHT, CAM_BACK; empty loads all six (those present)."""
    interpolate_frames: int = 4
    """Frames between two annotated keyframes (2 Hz): 4 gives the reference's 10 Hz, 0 loads keyframes only."""
    max_track_gap: MaxTrackGap = 1.0
    """Interpolate a box between annotations at most this many seconds apart (keyframes are 0.5 s apart, so 1.0 bridges one missed keyframe); across longer gaps the actor is absent."""
    lidar_min_distance: float = 1.0
    """Drop LiDAR returns within this horizontal distance (m) of the sensor (the ego car's roof), as the devkit does; 0 keeps all."""
    ego_mask_dir: Optional[Path] = None
    """Optional folder of <CHANNEL>.png masks (non-zero = the recording car, e.g. its trunk in CAM_BACK), left out of losses and metrics; cameras without a file get none."""
