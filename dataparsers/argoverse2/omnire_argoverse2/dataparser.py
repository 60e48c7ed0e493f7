"""Argoverse 2 reader: one sensor-dataset log in AV2's own layout -> :class:`SceneData`.

Frames are the LiDAR sweeps (``sensors/lidar/<timestamp_ns>.feather``, 10 Hz). For each
frame and camera the image nearest in time is taken (cameras run at 20 Hz, unsynchronised
with the sweeps) and its exact timestamp kept; the camera pose is the ego pose interpolated
to that timestamp (``city_SE3_egovehicle.feather`` holds poses at every sensor time) times
the camera's ``egovehicle_SE3_sensor``, which is OpenCV camera-to-ego already (see
:mod:`omnire_argoverse2.log` for the conventions and how they were checked). Boxes are
annotated at sweep times in the ego frame; they are carried to the world with the ego
pose of their sweep, and the core interpolates them to each camera's capture time.

World: z up, origin at the ego pose of the first loaded sweep, x along its heading
(``first_pose_world``); the city frame drops out.
"""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Type

import numpy as np

from omnire.api import (
    BYTE_INTENSITY, ActorTrack, CameraSequence, Dataparser, LidarSweeps, LogDataparserConfig, STATIONARY_THRESHOLD,
    SceneData, extend_poses, first_pose_world, frame_range, image_size, is_stationary, loaded_camera,
    majority_label, resample_track, thin_points,
)
from omnire_argoverse2 import log as av2
from omnire_argoverse2 import vlp32c
from omnire_argoverse2.log import Av2LogError
from omnire_argoverse2.vlp32c import laser_elevations

ATTRIBUTION = (
    '"Argoverse 2: Next Generation Datasets for Self-Driving Perception and Forecasting", Wilson et al., '
    "NeurIPS Datasets and Benchmarks 2021; Argoverse data by Argo AI, CC BY-NC-SA 4.0 (non-commercial)."
)


@dataclasses.dataclass
class Argoverse2Config(LogDataparserConfig):
    """Argoverse 2 sensor log in AV2's own layout (<split>/<log_id>/ with feather files)."""

    _target: Type = dataclasses.field(default_factory=lambda: Argoverse2Dataparser)
    data: Path = Path(".")
    """One AV2 sensor log directory (<split>/<log_id>/ holding city_SE3_egovehicle.feather, calibration/, sensors/)."""
    cameras: tuple[str, ...] = ()
    """Cameras to load by AV2 name (ring_front_center, ring_side_left, stereo_front_left, ...); empty: the seven ring cameras (those present)."""
    include_stereo: bool = False
    """With the default camera set, also load stereo_front_left and stereo_front_right."""
    max_camera_offset: float = 0.05
    """Largest |image time - sweep time| in seconds for the image nearest a sweep (cameras run at 20 Hz, so normally at most 0.025)."""
    max_track_gap: float = 0.35
    """Sweeps inside a track's annotated span but unannotated (occlusions) get poses interpolated when the annotations around them are at most this many seconds apart (cuboids come at 10 Hz); 0 interpolates nothing."""


class Argoverse2Dataparser(Dataparser):
    """Reads one AV2 sensor log (see the module docstring)."""

    config: Argoverse2Config

    def parse(self) -> SceneData:
        cfg = self.config
        root = Path(cfg.data)
        cfg.check()
        self._check_root(root)

        sweep_ns, sweep_paths = av2.sweep_files(root)
        frames = frame_range(cfg.start_frame, cfg.end_frame, len(sweep_ns), str(root / "sensors" / "lidar"))
        frame_ns = sweep_ns[frames.start:frames.stop]
        names = self.camera_names(root)  # fails early, naming the folder, when images are absent

        ego = av2.read_ego_poses(root)
        city_ego = ego.at(frame_ns)  # (F, 4, 4)
        world = first_pose_world(city_ego[0])  # (4, 4) city -> omnire world
        intrinsics = av2.read_intrinsics(root)
        sensors = av2.read_sensor_poses(root)

        cameras = [self._camera(root, n, frame_ns, ego, world, intrinsics, sensors) for n in names]
        lidar = None
        if cfg.load_lidar:
            up = av2.sensor_row(sensors, av2.LIDAR_SENSOR, root / "calibration" / "egovehicle_SE3_sensor.feather",
                                "LiDAR extrinsics, the origin of every sweep")
            lidar = load_lidar(sweep_paths[frames.start:frames.stop], frame_ns, world[None] @ city_ego, up,
                               cfg.max_lidar_points_per_frame)
        ann = av2.read_annotations(root)  # None in the AV2 test split: no actors
        tracks = [] if ann is None else load_tracks(ann, root / "annotations.feather", frame_ns, ego, world,
                                                    cfg.max_track_gap, cfg.stationary_threshold)
        return self.build_scene(f"av2_{root.resolve().name}", cameras, frame_ns * 1e-9,
                                np.arange(frames.start, frames.stop), lidar=lidar, tracks=tracks,
                                ego_poses=world[None] @ city_ego, attribution=ATTRIBUTION)

    # -- layout ------------------------------------------------------------------------------
    @staticmethod
    def _check_root(root: Path) -> None:
        if not root.is_dir():
            raise Av2LogError(f"{root}: AV2 log directory not found; expected <split>/<log_id>/ of the AV2 "
                              "sensor dataset (holding city_SE3_egovehicle.feather, calibration/, sensors/)")
        if not (root / "city_SE3_egovehicle.feather").is_file():
            logs = sorted(p.name for p in root.iterdir() if (p / "city_SE3_egovehicle.feather").is_file())
            hint = (f"; it holds logs ({', '.join(logs[:3])}{', ...' if len(logs) > 3 else ''}): pass one of them, "
                    f"e.g. --data {root / logs[0]}") if logs else ""
            raise Av2LogError(f"{root / 'city_SE3_egovehicle.feather'}: missing ego poses; --data must be one "
                              f"AV2 log directory{hint}")

    def camera_names(self, root: Path) -> list[str]:
        """The cameras to load: the configured ones, or the ring (+ stereo) cameras present.
        Raises :class:`Av2LogError` naming the missing camera folder(s)."""
        cfg = self.config
        cam_dir = root / "sensors" / "cameras"
        known = av2.RING_CAMERAS + av2.STEREO_CAMERAS
        present = [n for n in known if (cam_dir / n).is_dir()]
        if cfg.cameras:
            unknown = [n for n in cfg.cameras if n not in known]
            if unknown:
                raise Av2LogError(f"cameras: {unknown} are not AV2 cameras; AV2 cameras: {list(known)}")
            missing = [n for n in cfg.cameras if n not in present]
            if missing:
                raise Av2LogError(f"{cam_dir / missing[0]}: missing camera folder (no images of {missing[0]}); "
                                  f"cameras present in {cam_dir}: {present}")
            return list(cfg.cameras)
        wanted = av2.RING_CAMERAS + (av2.STEREO_CAMERAS if cfg.include_stereo else ())
        names = [n for n in wanted if n in present]
        missing = [n for n in wanted if n not in present]
        if not names:
            where = f"{cam_dir} does not exist" if not cam_dir.is_dir() else f"{cam_dir} holds none of them"
            raise Av2LogError(f"{cam_dir / wanted[0]}: missing camera folder: this log has no camera images "
                              f"({where}; expected sensors/cameras/<camera>/<timestamp_ns>.jpg for {list(wanted)})")
        if missing:
            warnings.warn(f"{cam_dir}: camera folders {missing} missing; loading {names}", stacklevel=2)
        return names

    # -- sensors -----------------------------------------------------------------------------
    def _camera(self, root: Path, name: str, frame_ns: np.ndarray, ego: av2.EgoPoses, world: np.ndarray,
                intrinsics: dict, sensors: dict) -> CameraSequence:
        cfg = self.config
        folder = root / "sensors" / "cameras" / name
        image_ns, paths = av2.timestamped_files(folder, ".jpg", f"{name} images")
        pick, offset = av2.nearest(frame_ns, image_ns)  # (F,), (F,) ns
        worst = int(np.argmax(np.abs(offset)))
        if abs(offset[worst]) > cfg.max_camera_offset * 1e9:
            raise Av2LogError(
                f"{folder}: the image nearest the sweep at timestamp_ns {int(frame_ns[worst])} is "
                f"{offset[worst] / 1e6:+.1f} ms away (limit --max-camera-offset {cfg.max_camera_offset} s); "
                "images missing around that sweep? Choose other frames or raise the limit"
            )
        calib = root / "calibration"
        intr = av2.sensor_row(intrinsics, name, calib / "intrinsics.feather", "camera intrinsics")
        cam_to_ego = av2.sensor_row(sensors, name, calib / "egovehicle_SE3_sensor.feather", "camera extrinsics")
        chosen = [paths[i] for i in pick]
        size = image_size(chosen[0])
        if size != (intr.width, intr.height):
            raise Av2LogError(f"{chosen[0]}: image is {size[0]}x{size[1]} but {calib / 'intrinsics.feather'} gives "
                              f"{name} width_px x height_px = {intr.width}x{intr.height}")
        cam_ns = image_ns[pick]
        return loaded_camera(  # AV2 centres pixels at integers (omnire_argoverse2.log.CameraIntrinsics)
            name, chosen, intr.matrix, size, cfg.scale, "integer",
            cam_to_world=world[None] @ ego.at(cam_ns) @ cam_to_ego[None],  # (F, 4, 4) OpenCV camera-to-world
            timestamps=cam_ns * 1e-9,
            distortion=intr.distortion,
            extras={"timestamp_ns": cam_ns, "offset_from_sweep_s": offset * 1e-9},
        )

def load_lidar(paths: list[Path], frame_ns: np.ndarray, ego_to_world: np.ndarray, lidar_to_ego: np.ndarray,
               max_points: int = 0) -> LidarSweeps:
    """Sweeps -> world points with their intensity (0-255 / 255) and time (the sweep's
    timestamp plus the point's ``offset_ns``), one file at a time.

    Args:
        paths: F sweep files (ego frame at the sweep time); frame_ns: (F,) their timestamps.
        ego_to_world: (F, 4, 4) ego pose at each sweep time; lidar_to_ego: (4, 4) up_lidar
            extrinsics (its pose at each sweep time is the sweep's ``sensor_to_world``).
        max_points: thin each sweep to at most this many points (seeded by its timestamp); 0 keeps all.
    Two VLP-32C (``laser_number`` 0-31 and 32-63) each with its own pose make one sweep:
    ``up_lidar``'s lasers are the beams (omnire_argoverse2/vlp32c.py), ``down_lidar``'s
    returns have beam -1. Sweeps whose laser numbers do not show the VLP-32C's angles get no
    beams.
    """
    points, intensity, times, lasers = [], [], [], []
    for path, ts, M in zip(paths, frame_ns, ego_to_world):
        sweep = av2.read_sweep(path)
        keep = thin_points(np.arange(len(sweep.xyz)), max_points, ts)
        xyz = sweep.xyz[keep]  # (N, 3) ego frame
        points.append((xyz @ M[:3, :3].T + M[:3, 3]).astype(np.float32))
        intensity.append(BYTE_INTENSITY.to_unit(np.asarray(sweep.intensity)[keep], f"{path}: column intensity",
                                                Av2LogError))
        times.append((int(ts) + np.asarray(sweep.offset_ns, dtype=np.int64)[keep]) * 1e-9)
        lasers.append(np.asarray(sweep.laser_number)[keep])
    sensor_to_world = ego_to_world @ lidar_to_ego[None]  # (F, 4, 4), axes x forward, y left, z up
    # the sweeps start at their timestamp and last one revolution: extrapolate the track past the last one
    track = extend_poses(np.asarray(frame_ns, dtype=np.int64) * 1e-9, sensor_to_world, 0.2)
    first = slice(0, min(3, len(points)))  # three sweeps hold thousands of returns per laser
    elevations = laser_elevations(np.concatenate(points[first]).astype(np.float64), np.concatenate(times[first]),
                                  np.concatenate(lasers[first]), *track) if points else None
    return LidarSweeps(points=points, origins=sensor_to_world[:, :3, 3].copy(), intensity=intensity, times=times,
                       sensor_to_world=sensor_to_world,
                       beams=None if elevations is None else [vlp32c.beams_of(k) for k in lasers],
                       beam_model=None if elevations is None else vlp32c.beam_model(elevations))


def load_tracks(ann: av2.Annotations, path: Path, frame_ns: np.ndarray, ego: av2.EgoPoses, world: np.ndarray,
                max_track_gap: float = 0.35, stationary_threshold: float = STATIONARY_THRESHOLD) -> list[ActorTrack]:
    """Cuboid annotations -> one :class:`ActorTrack` per track uuid present in the frames.

    Args:
        ann: the log's annotations (``path`` is their file, for messages).
        frame_ns: (F,) sweep timestamps of the loaded frames.
        ego: the log's ego poses; world: (4, 4) city -> omnire world.
        max_track_gap: unannotated frames inside a track's span are interpolated when the
            annotations around them are at most this many seconds apart.
        stationary_threshold: metres of net motion below which a track is stationary
            (``omnire.api.is_stationary``).
    Poses are box-to-world at the frame times; ``extras["annotated"]`` (F,) marks frames
    with a cuboid of that sweep, ``extras["num_interior_pts"]`` (F,) its LiDAR count (-1 elsewhere).
    """
    F = len(frame_ns)
    if len(ann.timestamps_ns) == 0:
        return []
    # Every cuboid of the log to the world with the ego pose of its own sweep: annotations
    # just outside the loaded range still bound the interpolation inside it.
    box_to_world = world[None] @ ego.at(ann.timestamps_ns) @ ann.ego_SE3_box  # (N, 4, 4)
    query = (frame_ns - frame_ns[0]).astype(np.float64) * 1e-9
    tracks = []
    order = np.lexsort((ann.timestamps_ns, ann.track_uuid))
    uuids, starts = np.unique(ann.track_uuid[order], return_index=True)
    for uuid, rows in zip(uuids, np.split(order, starts[1:])):
        ts = ann.timestamps_ns[rows]
        if np.any(np.diff(ts) == 0):
            raise Av2LogError(f"{path}: track_uuid {uuid} has two cuboids at timestamp_ns "
                              f"{int(ts[np.flatnonzero(np.diff(ts) == 0)[0]])}")
        exact = np.isin(frame_ns, ts)
        times = (ts - frame_ns[0]).astype(np.float64) * 1e-9
        poses, present = resample_track(times, box_to_world[rows], query, max_track_gap)
        if not present.any():
            continue
        label = majority_label(ann.category[rows])
        interior = np.full(F, -1, np.int64)
        interior[exact] = ann.num_interior_pts[rows][np.searchsorted(ts, frame_ns[exact])]
        stationary = is_stationary(poses[present, :3, 3], stationary_threshold)
        tracks.append(ActorTrack(str(uuid), label, av2.category_of(label), poses, ann.size[rows].max(axis=0), present,
                                 stationary, extras={"annotated": exact, "num_interior_pts": interior}))
    return tracks



def read_log(data: Path, **overrides) -> SceneData:
    """Convenience: parse one log with :class:`Argoverse2Config` defaults plus ``overrides``."""
    return Argoverse2Dataparser(Argoverse2Config(data=Path(data), **overrides)).parse()


__all__ = ["ATTRIBUTION", "Argoverse2Config", "Argoverse2Dataparser", "load_lidar", "load_tracks", "read_log"]
