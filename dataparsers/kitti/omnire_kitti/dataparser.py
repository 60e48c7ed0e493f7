"""KITTI tracking reader: one sequence of the KITTI tracking benchmark, read in place ->
:class:`SceneData`.

Layout read (``--data`` is the tracking root holding training/ and testing/, or one of them)::

    <split>/image_02/<seq>/<frame:06d>.png    left colour camera, rectified
    <split>/image_03/<seq>/<frame:06d>.png    right colour camera, rectified (separate download)
    <split>/velodyne/<seq>/<frame:06d>.bin    float32 rows x y z reflectance, Velodyne frame
    <split>/calib/<seq>.txt                   P0..P3 (3x4), R_rect (3x3), Tr_velo_cam, Tr_imu_velo (3x4)
    <split>/oxts/<seq>.txt                    one line of 30 GPS/IMU values per frame
    <split>/label_02/<seq>.txt                tracked boxes (training split only)

Conventions (KITTI devkit readmes and "Vision meets Robotics: The KITTI Dataset", IJRR 2013):

- Frames: one per oxts line, 10 Hz; the cameras are triggered by the Velodyne when it faces
  forward, so camera and frame timestamps are the same (frame / ``fps``; the tracking release
  has no timestamp files).
- Poses: the IMU frame (x forward, y left, z up) is the ego frame. Its pose comes from the
  oxts line as in the devkit's convertOxtsToPose: Mercator projection with the scale
  cos(latitude of the first line) (x = scale * lon * pi * r / 180, y = scale * r *
  log(tan((90 + lat) * pi / 360)), r = 6378137 m, z = altitude) and R = Rz(yaw) Ry(pitch)
  Rx(roll).
- Calibration: a Velodyne point p maps to rectified camera-0 coordinates as R_rect @
  Tr_velo_cam @ p (Tr_imu_velo maps IMU to Velodyne). The rectified cameras share one
  orientation (OpenCV axes) and P_i = K_i [I | t_i]: camera i sits at -t_i in rectified
  camera-0 coordinates, t_i = K_i^-1 P_i[:, 3] (the stereo baseline lives there). Images are
  rectified and undistorted: no distortion coefficients.
- LiDAR: the Velodyne (HDL-64E) frame is x forward, y left, z up: ``sensor_to_world`` is it
  at the frame's time; reflectance (0-1) is the intensity. The files hold no per-point time
  (``times`` is None) and no laser index, and the HDL-64E's elevations are per-unit
  calibration values KITTI does not publish: the 64 beams are the scan lines of the files'
  order (a scan is stored laser by laser), their elevations measured from the loaded sweeps
  (omnire_kitti/hdl64e.py); they give ``beams`` and ``beam_model``; when neither the order
  nor the elevations give 64 beams both stay None and one warning says why.
- Pixels: the devkit gives 2D boxes "in the image (0-based index)" in the same pixel
  coordinates P_i projects to, i.e. pixel centres at integers; K gets +0.5 px for omnire.
- Labels: per row frame, track id, type, truncated, occluded, alpha, 2D box (4), dimensions
  (height, width, length), location (x, y, z of the bottom centre in rectified camera-0
  coordinates), rotation_y (about the camera's y axis, down) [, score]. The box's length runs
  along its object x axis (cos ry, 0, -sin ry) in camera coordinates. omnire boxes: centre
  moved up by height / 2 (camera y points down), x along that heading, z up (-y of the
  camera), size (length, width, height). DontCare rows (track id -1) are skipped.
"""
from __future__ import annotations

import dataclasses
import re
import warnings
from pathlib import Path
from typing import Literal, Optional, Type

import numpy as np

from omnire.api import (
    UNIT_INTENSITY, ActorTrack, CameraSequence, ConfigError, Dataparser, LidarSweeps, LogDataparserConfig, MaxTrackGap,
    SceneData, SceneDataError, axis_rotation, first_pose_world, frame_range, image_size, is_stationary, loaded_camera,
    majority_label, require_files, resample_track, thin_points,
)

from omnire_kitti import hdl64e

CAMERAS = ("image_02", "image_03")
"""KITTI colour cameras: left (P2) and right (P3)."""
EARTH_RADIUS = 6378137.0
"""Earth radius (m) of the devkit's Mercator projection."""
OXTS_VALUES = 30
LABEL_COLUMNS = 17
"""Columns of a label_02 row (an 18th, the score, appears in results files)."""

ATTRIBUTION = (
    '"Vision meets Robotics: The KITTI Dataset", Geiger, Lenz, Stiller and Urtasun, IJRR 2013; '
    "KITTI Vision Benchmark Suite, CC BY-NC-SA 3.0."
)
_CALIB_KEYS = {
    "P0": ("P0",), "P1": ("P1",), "P2": ("P2",), "P3": ("P3",),
    "R_rect": ("R_rect", "R0_rect"), "Tr_velo_cam": ("Tr_velo_cam", "Tr_velo_to_cam"),
    "Tr_imu_velo": ("Tr_imu_velo", "Tr_imu_to_velo"),
}
_VEHICLE = frozenset({"Car", "Van", "Truck", "Tram"})
_HUMAN = frozenset({"Pedestrian", "Person_sitting", "Person"})
# Camera axes (x right, y down, z forward) of the KITTI object frame -> omnire box axes
# (x along the length, y left, z up): columns are the omnire axes in object coordinates.
_BOX_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class KittiDataError(SceneDataError):
    """A KITTI file is malformed or inconsistent (the message names the file and field)."""


class KittiFileMissing(KittiDataError, FileNotFoundError):
    """A KITTI file is missing (the message names the path)."""


def category_of(label: str) -> str:
    """KITTI object type -> omnire actor category (vehicle, human, cyclist, other)."""
    if label in _VEHICLE:
        return "vehicle"
    if label in _HUMAN:
        return "human"
    if label == "Cyclist":
        return "cyclist"
    return "other"  # Misc


# ----------------------------------------------------------------------------- files
def read_calib(path: Path) -> dict[str, np.ndarray]:
    """KITTI tracking calibration -> {P0..P3: (3, 4), R_rect: (3, 3), Tr_velo_cam,
    Tr_imu_velo: (4, 4)}. Accepts the tracking keys (``R_rect``, ``Tr_velo_cam``) and the
    object-benchmark ones (``R0_rect:``, ``Tr_velo_to_cam:``), with or without colons."""
    if not path.is_file():
        raise KittiFileMissing(f"{path}: missing calibration file (P0-P3, R_rect, Tr_velo_cam, Tr_imu_velo)")
    raw: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        parts = line.replace(":", " ", 1).split()
        if parts:
            raw[parts[0]] = parts[1:]
    out = {}
    for key, aliases in _CALIB_KEYS.items():
        name = next((a for a in aliases if a in raw), None)
        if name is None:
            raise KittiDataError(f"{path}: no {key} line (also accepted: {', '.join(aliases[1:]) or 'none'})")
        n = 9 if key == "R_rect" else 12
        try:
            vals = np.array([float(v) for v in raw[name]], dtype=np.float64)
        except ValueError:
            raise KittiDataError(f"{path}: {name} has a non-numeric value; expected {n} numbers") from None
        if vals.size != n or not np.isfinite(vals).all():
            raise KittiDataError(f"{path}: {name} has {vals.size} values, expected {n} finite numbers")
        if key == "R_rect":
            out[key] = vals.reshape(3, 3)
        elif key.startswith("P"):
            out[key] = vals.reshape(3, 4)
        else:
            out[key] = np.vstack([vals.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    return out


def split_projection(P: np.ndarray, path: Path, key: str) -> tuple[np.ndarray, np.ndarray]:
    """Rectified projection P (3, 4) = K [I | t] -> (K (3, 3), t (3,))."""
    K = P[:, :3]
    if not (K[1, 0] == 0 and K[2, 0] == 0 and K[2, 1] == 0 and K[2, 2] == 1 and K[0, 0] > 0 and K[1, 1] > 0):
        raise KittiDataError(f"{path}: {key} = {P.tolist()} is not a rectified projection K [I | t] with "
                             "K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    return K.copy(), np.linalg.solve(K, P[:, 3])


def read_oxts(path: Path) -> np.ndarray:
    """(N, 30) float64 oxts values, one row per frame."""
    if not path.is_file():
        raise KittiFileMissing(f"{path}: missing GPS/IMU (oxts) file, one line of {OXTS_VALUES} values per frame")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise KittiDataError(f"{path}: line {n} has a non-numeric value; expected {OXTS_VALUES} numbers "
                                 "(lat lon alt roll pitch yaw vn ve vf vl vu ax ay az af al au wx wy wz wf wl wu "
                                 "posacc velacc navstat numsats posmode velmode orimode)") from None
        if len(vals) != OXTS_VALUES or not np.isfinite(vals[:6]).all():
            raise KittiDataError(f"{path}: line {n} has {len(vals)} values, expected {OXTS_VALUES} "
                                 "(lat lon alt roll pitch yaw ... orimode), the first six finite")
        rows.append(vals)
    if not rows:
        raise KittiDataError(f"{path}: no oxts lines (the frame count of a sequence is its number of oxts lines)")
    return np.asarray(rows, dtype=np.float64)


def oxts_poses(oxts: np.ndarray) -> np.ndarray:
    """(N, 30) oxts rows -> (N, 4, 4) IMU-to-world in the devkit's Mercator frame (x east,
    y north, z up, metres), scale from the first row's latitude."""
    lat, lon, alt, roll, pitch, yaw = (oxts[:, i] for i in range(6))
    scale = np.cos(np.deg2rad(lat[0]))
    out = np.tile(np.eye(4), (len(oxts), 1, 1))
    out[:, 0, 3] = scale * lon * np.pi * EARTH_RADIUS / 180.0
    out[:, 1, 3] = scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat) * np.pi / 360.0))
    out[:, 2, 3] = alt
    out[:, :3, :3] = axis_rotation(2, yaw) @ axis_rotation(1, pitch) @ axis_rotation(0, roll)
    return out


def label_box(h: float, w: float, l: float, x: float, y: float, z: float, ry: float) -> np.ndarray:
    """One label row's box -> (4, 4) box-to-rectified-camera-0 with the origin at the box
    centre, x along the heading, z up."""
    R = axis_rotation(1, np.array([ry]))[0]  # object -> camera: rotation about the camera y axis
    T = np.eye(4)
    T[:3, :3] = R @ _BOX_AXES
    T[:3, 3] = (x, y - h / 2.0, z)  # bottom centre -> centre (camera y points down)
    return T


def read_labels(path: Path, num_frames: int) -> dict[str, list[tuple[int, str, np.ndarray, np.ndarray]]]:
    """label_02 rows by track id: [(frame, type, box-to-rect (4, 4), size (l, w, h))];
    DontCare rows and track id -1 skipped."""
    tracks: dict[str, list] = {}
    seen = set()
    for n, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        where = f"{path}: line {n}"
        if len(parts) not in (LABEL_COLUMNS, LABEL_COLUMNS + 1):
            raise KittiDataError(f"{where} has {len(parts)} columns, expected {LABEL_COLUMNS} (frame, track id, type, "
                                 "truncated, occluded, alpha, bbox left top right bottom, height width length, "
                                 "x y z, rotation_y [, score])")
        kind = parts[2]
        if kind == "DontCare":
            continue
        try:
            frame, tid = int(parts[0]), int(parts[1])
            h, w, l, x, y, z, ry = (float(v) for v in parts[10:17])
        except ValueError:
            raise KittiDataError(f"{where}: frame and track id must be integers and dimensions, location, "
                                 "rotation_y numbers") from None
        if tid < 0:
            continue
        if not 0 <= frame < num_frames:
            raise KittiDataError(f"{where}: frame {frame} outside the sequence's 0..{num_frames - 1} (oxts lines)")
        if not (h > 0 and w > 0 and l > 0) or not np.isfinite([x, y, z, ry]).all():
            raise KittiDataError(f"{where}: track {tid} ({kind}) has dimensions {h} {w} {l} (height width length "
                                 f"must be positive) or a non-finite location/rotation_y")
        if (frame, tid) in seen:
            raise KittiDataError(f"{where}: track {tid} appears twice in frame {frame}")
        seen.add((frame, tid))
        tracks.setdefault(str(tid), []).append((frame, kind, label_box(h, w, l, x, y, z, ry), np.array([l, w, h])))
    return tracks


# ----------------------------------------------------------------------------- dataparser
class KittiDataparser(Dataparser):
    """Reads one KITTI tracking sequence (see the module docstring)."""

    config: "KittiConfig"

    def parse(self) -> SceneData:
        cfg = self.config
        self._check_options()
        split = self._split_dir()
        seq = self._sequence()
        calib_path = split / "calib" / f"{seq}.txt"
        calib = read_calib(calib_path)
        oxts = read_oxts(split / "oxts" / f"{seq}.txt")
        n_log = len(oxts)
        rng = frame_range(cfg.start_frame, cfg.end_frame, n_log, f"KITTI sequence {seq} ({split})")
        frames = np.arange(rng.start, rng.stop)
        imu_poses = oxts_poses(oxts)  # (N, 4, 4) IMU -> Mercator world
        world = first_pose_world(imu_poses[rng.start])
        # Rectified camera 0 -> IMU: inverse of (R_rect Tr_velo_cam Tr_imu_velo).
        R_rect = np.eye(4)
        R_rect[:3, :3] = calib["R_rect"]
        imu_from_rect = np.linalg.inv(R_rect @ calib["Tr_velo_cam"] @ calib["Tr_imu_velo"])
        imu_from_velo = np.linalg.inv(calib["Tr_imu_velo"])
        rect_to_world = world[None] @ imu_poses[frames] @ imu_from_rect  # (F, 4, 4)
        times = frames / cfg.fps

        cameras = [self._camera(split, seq, name, calib, calib_path, rect_to_world, frames, times)
                   for name in self._camera_names(split, seq)]
        lidar = self._lidar(split, seq, frames, world[None] @ imu_poses[frames] @ imu_from_velo) if cfg.load_lidar else None
        tracks = self._tracks(split / "label_02" / f"{seq}.txt", n_log, frames, times, rect_to_world)
        return self.build_scene(f"kitti_{split.name}_{seq}", cameras, times, frames, lidar=lidar, tracks=tracks,
                                ego_poses=world[None] @ imu_poses[frames], attribution=ATTRIBUTION)

    # -- options -------------------------------------------------------------------------------
    def _check_options(self) -> None:
        cfg = self.config
        cfg.check()
        if not cfg.fps > 0:
            raise ConfigError(f"fps: {cfg.fps}, expected a positive frame rate (KITTI records at 10 Hz)")
        bad = [c for c in cfg.cameras if c not in CAMERAS]
        if bad:
            raise ConfigError(f"cameras: {bad} are not KITTI colour cameras; choose from {list(CAMERAS)}")

    def _split_dir(self) -> Path:
        data = Path(self.config.data)
        if not data.is_dir():
            raise KittiFileMissing(f"{data}: KITTI tracking folder does not exist; expected the folder holding "
                                   "training/ and testing/ (or one of them, with image_02/, calib/, oxts/, ...)")
        if (data / "calib").is_dir() or (data / "oxts").is_dir():
            return data
        split = data / self.config.split
        if not split.is_dir():
            found = sorted(p.name for p in data.iterdir() if p.is_dir())
            raise KittiFileMissing(f"{split}: no such split folder (--split {self.config.split}); folders in {data}: "
                                   f"{found or 'none'}")
        return split

    def _sequence(self) -> str:
        seq = str(self.config.sequence).strip()
        if not re.fullmatch(r"\d{1,4}", seq):
            raise ConfigError(f"sequence: {self.config.sequence!r}, expected a sequence number such as 0000 or 7")
        return seq.zfill(4)

    def _camera_names(self, split: Path, seq: str) -> list[str]:
        present = [c for c in CAMERAS if (split / c / seq).is_dir()]
        if not self.config.cameras:
            if not present:
                raise KittiFileMissing(f"{split / 'image_02' / seq}: no image folder for sequence {seq} "
                                       "(neither image_02 nor image_03)")
            return present
        missing = [c for c in self.config.cameras if c not in present]
        if missing:
            raise KittiFileMissing(f"{split / missing[0] / seq}: missing (cameras {missing} requested; present for "
                                   f"sequence {seq}: {present})")
        return list(self.config.cameras)

    # -- sensors ---------------------------------------------------------------------------------
    def _camera(self, split: Path, seq: str, name: str, calib: dict, calib_path: Path, rect_to_world: np.ndarray,
                frames: np.ndarray, times: np.ndarray) -> CameraSequence:
        key = "P" + name[-1]
        K0, t = split_projection(calib[key], calib_path, key)
        cam_to_rect = np.eye(4)
        cam_to_rect[:3, 3] = -t  # camera centre in rectified camera-0 coordinates
        paths = [split / name / seq / f"{f:06d}.png" for f in frames]
        require_files(paths, f"image of {name}", KittiFileMissing)
        return loaded_camera(name, paths, K0, image_size(paths[0]), self.config.scale, "integer",
                             cam_to_world=rect_to_world @ cam_to_rect,  # rectified axes are OpenCV's
                             timestamps=times.copy(),  # triggered by the Velodyne: the frame time
                             distortion=None)  # rectified images

    def _lidar(self, split: Path, seq: str, frames: np.ndarray, velo_to_world: np.ndarray) -> Optional[LidarSweeps]:
        cfg = self.config
        folder = split / "velodyne" / seq
        if not folder.is_dir():
            raise KittiFileMissing(f"{folder}: missing Velodyne folder of sequence {seq} (--no-load-lidar skips LiDAR)")
        points: list[Optional[np.ndarray]] = []
        reflectance: list[Optional[np.ndarray]] = []
        lines: list[Optional[np.ndarray]] = []
        sensor_to_world = np.full((len(frames), 4, 4), np.nan)
        for j, f in enumerate(frames):
            path = folder / f"{f:06d}.bin"
            if not path.is_file():  # real gaps exist (training 0001 lacks frames 177-180)
                points.append(None)
                reflectance.append(None)
                lines.append(None)
                continue
            size = path.stat().st_size
            if size % 16:
                raise KittiDataError(f"{path}: {size} bytes is not a whole number of 16-byte points "
                                     "(4 float32: x y z reflectance)")
            rows = np.fromfile(path, dtype="<f4").reshape(-1, 4).astype(np.float64)  # (N, 4) Velodyne frame
            if not np.isfinite(rows).all():
                raise KittiDataError(f"{path}: non-finite values")
            rows[:, 3] = UNIT_INTENSITY.to_unit(rows[:, 3], f"{path}: column 4 (reflectance)", KittiDataError)
            rows = np.column_stack([rows, hdl64e.scan_lines(rows[:, :3])])  # counted in file order, before thinning
            rows = thin_points(rows, cfg.max_lidar_points_per_frame, f)  # keyed by the frame of the log
            lines.append(rows[:, 4].astype(np.int64))
            M = velo_to_world[j]  # the Velodyne's axes are x forward, y left, z up already
            points.append((rows[:, :3] @ M[:3, :3].T + M[:3, 3]).astype(np.float32))
            reflectance.append(rows[:, 3].astype(np.float32))
            sensor_to_world[j] = M
        fit = hdl64e.measure_beams(points, sensor_to_world, lines) if cfg.estimate_beams else None
        if fit is not None and fit.model is None:
            warnings.warn(f"{folder}: the sweeps get no beams: {fit.reason} (--no-estimate-beams skips the "
                          "measurement)", stacklevel=3)
        trusted = fit is not None and fit.model is not None
        return LidarSweeps(points=points, origins=sensor_to_world[:, :3, 3].copy(), intensity=reflectance,
                           sensor_to_world=sensor_to_world, beams=fit.beams if trusted else None,
                           beam_model=fit.model if trusted else None)

    def _tracks(self, path: Path, n_log: int, frames: np.ndarray, times: np.ndarray,
                rect_to_world: np.ndarray) -> list[ActorTrack]:
        if not path.is_file():  # the testing split has no labels
            return []
        cfg = self.config
        local = {int(f): i for i, f in enumerate(frames)}
        tracks = []
        for tid, rows in sorted(read_labels(path, n_log).items(), key=lambda kv: int(kv[0])):
            rows = sorted((r for r in rows if r[0] in local), key=lambda r: r[0])
            if not rows:
                continue
            idx = np.array([local[r[0]] for r in rows])
            boxes = np.stack([rect_to_world[i] @ r[2] for i, r in zip(idx, rows)])  # (K, 4, 4) box -> world
            poses, present = resample_track(times[idx], boxes, times, cfg.max_track_gap)
            label = majority_label([r[1] for r in rows])
            size = np.max([r[3] for r in rows], axis=0)
            stationary = is_stationary(poses[present, :3, 3], cfg.stationary_threshold)
            tracks.append(ActorTrack(tid, label, category_of(label), poses, size, present, stationary,
                                     extras={"labelled_frames": idx}))
        return tracks



@dataclasses.dataclass
class KittiConfig(LogDataparserConfig):
    """One sequence of the KITTI tracking benchmark (image_02/03, velodyne, calib, oxts, label_02)."""

    _target: Type = dataclasses.field(default_factory=lambda: KittiDataparser)
    data: Path = Path("data/kitti/tracking")
    """KITTI tracking folder holding training/ and testing/, or one split folder itself."""
    split: Literal["training", "testing"] = "training"
    """Split folder under --data (testing has no labels)."""
    sequence: str = "0000"
    """Sequence number (file names such as calib/0000.txt); 7 and 0007 are the same."""
    cameras: tuple[str, ...] = ()
    """Cameras to load: image_02 (left colour), image_03 (right colour); empty loads those present."""
    fps: float = 10.0
    """Frame rate of the sequence (KITTI: 10 Hz); timestamps are frame / fps."""
    max_track_gap: MaxTrackGap = 0.5
    """Interpolate a track across unlabelled frames when the labels around them are at most this many seconds apart (labels come at 10 Hz); across longer gaps the actor is absent. 0 keeps the labelled frames only."""
    estimate_beams: bool = True
    """Measure the HDL-64E's 64 beams from the sweeps and give every return its beam (omnire_kitti/hdl64e.py); --no-estimate-beams leaves the sweeps without beams."""
