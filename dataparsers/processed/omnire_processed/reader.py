"""Dataparser for the reference implementation's processed-scene format (docs/conventions.md).

Conversions to omnire's conventions (docs/conventions.md):

- World: every world-frame quantity is re-expressed relative to the ego pose (``ego_pose/``,
  or ``lidar_pose/`` for nuScenes-style scenes) of the first loaded frame, so the file's
  world (UTM, a y-down camera-aligned world, anything) drops out. With ``up_axis=auto`` the
  reader then checks the cameras' up vectors (-y of OpenCV cameras, averaged) and, if they
  are more than 30 degrees from +z (an ego frame that is not z-up, e.g. camera-like),
  turns the ego axis nearest to that up direction to +z.
- Cameras: per-camera ``extrinsics/{cam}.txt`` are camera->ego (Waymo camera axes are
  converted by right-multiplying ``WAYMO_TO_OPENCV``); per-frame
  ``extrinsics/{t:03d}_{cam}.txt`` are camera->world in OpenCV axes (nuScenes, PandaSet).
- Intrinsics: 9 numbers ``fx fy cx cy k1 k2 p1 p2 k3`` at the image files' resolution, the
  dataset's own values (the reference copies them unchanged), so in the dataset's pixel-centre
  convention (``formats.PIXEL_CENTRES``, with the evidence): Waymo, PandaSet and nuScenes
  centre pixel (i, j) at (i + 0.5, j + 0.5) like omnire, used as is; Argoverse2, KITTI and
  NuPlan (and ``file_pixel_centres=integer``) centre it at (i, j) as OpenCV does, so +0.5 px
  is added to cx, cy. Then K is scaled to the loaded size (continuous coordinates scale by
  plain multiplication). Distortion is ignored (reported once if non-zero).
- LiDAR: columns per dataset (``formats.LIDAR_LAYOUTS``), points posed by the frame's ego
  (or LiDAR) pose; intensity mapped from the source dataset's scale, which the files keep,
  to [0, 1] (``LidarLayout.intensity_scale``).
- Boxes: ``obj_to_world`` is box-to-world at the box centre and ``box_size`` the extents
  along the box's local x, y, z. The reference writes local x along the heading with
  box_size = (length, width, height) for Waymo, nuScenes, Argoverse2, KITTI and NuPlan, but
  keeps PandaSet's own box frame, whose local +y is the heading (box_size = (width, length,
  height)); see ``formats.BOX_HEADING_AXIS`` for what each preprocessing writes. The file does
  not say which, so with ``box_heading_axis=auto`` the reader checks it
  (``boxes.detect_heading_axis``: the direction moving boxes travel in, in their own frame,
  and which horizontal extent of vehicle boxes is the longer), falls back to the source's
  convention with a warning when the file is ambiguous, and warns when the file contradicts
  it. Boxes are then turned about their z axis so that x is the heading and the size is
  (length, width, height).
- SMPL: ``global_orient`` given in the OpenCV frame of camera ``selected_cam_idx[t]`` is
  turned into body-to-world with that camera's converted camera->world rotation.

``source=auto`` picks the dataset as follows: per-frame extrinsics with ``lidar_pose/`` ->
nuScenes; per-frame extrinsics with ``ego_pose/`` -> PandaSet; per-camera extrinsics: the
class names in instances_info.json if they single out a dataset, else the LiDAR column
count (14 Waymo, 6 NuPlan, 5 PandaSet, 4 Argoverse/KITTI-like), and Waymo camera axes are
also recognised from the extrinsics (camera z pointing up in the ego frame).
"""
from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path
from typing import Literal, Optional, Type

import numpy as np

from omnire.api import (
    STATIONARY_THRESHOLD, ActorTrack, CameraSequence, Dataparser, DataparserConfig, HumanPoseSequence, LidarSweeps,
    SceneData, SceneDataError, image_size, is_stationary, loaded_camera,
)

from omnire_processed import boxes, formats
from omnire_processed.formats import LIDAR_LAYOUTS, WAYMO_TO_OPENCV, category_of

Source = Literal["auto", "waymo", "nuscenes", "nuplan", "argoverse", "pandaset", "kitti"]
IMAGE_EXTS = (".jpg", ".jpeg", ".png")


class ProcessedSceneError(SceneDataError):
    """The scene folder is incomplete or a file is malformed (the message names the file)."""


def _load_matrix(path: Path) -> np.ndarray:
    if not path.is_file():
        raise ProcessedSceneError(f"{path}: missing")
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise ProcessedSceneError(f"{path}: not a whitespace-separated matrix ({exc})") from None
    if m.size != 16:
        raise ProcessedSceneError(f"{path}: expected a 4x4 matrix (16 numbers), found {m.size}")
    m = m.reshape(4, 4)
    if not np.isfinite(m).all():
        raise ProcessedSceneError(f"{path}: contains NaN or inf")
    return m



def _to_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor from a reference-implementation pickle
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking unit vector a to unit vector b (shortest arc)."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-9:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


@dataclasses.dataclass
class ProcessedDataparserConfig(DataparserConfig):
    """Reads a scene in the reference implementation's processed format."""

    _target: Type = dataclasses.field(default_factory=lambda: ProcessedDataparser)
    source: Source = "auto"
    """Dataset the scene was processed from (LiDAR columns, camera axes, class/camera names); auto detects it."""
    cameras: tuple[int, ...] = ()
    """Camera ids to load (file names in intrinsics/); empty loads all."""
    start_frame: int = 0
    """First frame of the log to load."""
    end_frame: int = -1
    """One past the last frame to load; -1 loads to the end."""
    fps: float = 10.0
    """Frame rate of the processed log (timestamps are frame / fps)."""
    load_lidar: bool = True
    """Load LiDAR sweeps from lidar/."""
    lidar_sensor_ids: tuple[int, ...] = ()
    """PandaSet only: keep these sensor ids (0 = 360-degree LiDAR, 1 = front LiDAR); empty keeps all."""
    load_human_poses: bool = True
    """Load humanpose/smpl.pkl when present."""
    prefer_fine_masks: bool = True
    """Use fine_dynamic_masks/ instead of dynamic_masks/ when present."""
    up_axis: Literal["auto", "ego"] = "auto"
    """auto: if the cameras' mean up is over 30 deg from +z, turn the nearest ego axis up; ego: trust the ego frame."""
    stationary_threshold: float = STATIONARY_THRESHOLD
    """A track is stationary when the medians of its box centres over the first and last thirds of its loaded frames are less than this many metres apart (unless the file flags it)."""
    file_pixel_centres: Literal["auto", "half", "integer"] = "auto"
    """Pixel-centre convention of intrinsics/: auto by source; half: pixel (i, j) centred at (i+0.5, j+0.5) (used as is); integer: at (i, j) as in OpenCV (+0.5 added)."""
    box_heading_axis: Literal["auto", "+x", "+y", "-x", "-y"] = "auto"
    """Local axis of the file's boxes that points along the heading; auto checks the boxes' motion and shapes."""


class ProcessedDataparser(Dataparser):
    """See the module docstring."""

    config: ProcessedDataparserConfig

    def __init__(self, config: ProcessedDataparserConfig) -> None:
        super().__init__(config)
        self.source: Optional[str] = None
        self.world_from_file: Optional[np.ndarray] = None
        self.heading_axis: Optional[boxes.HeadingAxis] = None
        self.pixel_centres: Optional[str] = None
        self.notes: list[str] = []

    # ------------------------------------------------------------------ layout
    def parse(self) -> SceneData:
        cfg = self.config
        cfg.check()
        root = Path(cfg.data)
        if not root.is_dir():
            raise ProcessedSceneError(f"{root}: scene folder not found")
        pose_dir = root / "ego_pose"
        if not pose_dir.is_dir():
            pose_dir = root / "lidar_pose"
            if not pose_dir.is_dir():
                raise ProcessedSceneError(
                    f"{root / 'ego_pose'}: missing (the frame count and ego poses come from ego_pose/, "
                    "or lidar_pose/ for nuScenes-style scenes)"
                )
        n_full = len(list(pose_dir.glob("*.txt")))
        if n_full == 0:
            raise ProcessedSceneError(f"{pose_dir}: no pose files")
        start = cfg.start_frame
        end = n_full if cfg.end_frame < 0 else min(cfg.end_frame, n_full)
        if not 0 <= start < end:
            raise ProcessedSceneError(f"{root}: frame range {start}..{end} is empty (log has {n_full} frames)")
        poses_file = np.stack([_load_matrix(pose_dir / f"{t:03d}.txt") for t in range(n_full)])  # (N, 4, 4)
        frames = np.arange(start, end)

        cam_ids = self._camera_ids(root)
        per_frame = self._extrinsics_layout(root, cam_ids[0])
        source = self._detect_source(root, pose_dir, per_frame, cam_ids, poses_file)
        self.source = source

        # World alignment: the first loaded ego pose becomes the origin.
        align = np.linalg.inv(poses_file[start])
        c2w_file = {c: self._cam_to_world_file(root, c, per_frame, source, poses_file) for c in cam_ids}
        if cfg.up_axis == "auto":
            ups = np.concatenate([-(align[:3, :3] @ c2w_file[c][frames, :3, :3])[..., 1] for c in cam_ids])
            up = ups.mean(0)
            up /= max(np.linalg.norm(up), 1e-12)
            if up[2] < np.cos(np.deg2rad(30.0)):
                # Ego frames are axis-aligned with gravity (camera-like, y down, in practice), so
                # turn the ego axis nearest to the cameras' up to +z; the cameras' own pitch
                # must not tilt the world.
                k = int(np.argmax(np.abs(up)))
                axis = np.zeros(3)
                axis[k] = np.sign(up[k])
                fix = np.eye(4)
                fix[:3, :3] = _rotation_between(axis, np.array([0.0, 0.0, 1.0]))
                align = fix @ align
                self.notes.append(f"ego frame is not z-up (camera up {np.round(up, 3).tolist()}); world rotated to z-up")
        self.world_from_file = align

        cameras = [self._camera(root, c, c2w_file[c][frames], align, frames, source) for c in cam_ids]
        timestamps = frames / cfg.fps
        ego_poses = align @ poses_file[frames]

        lidar = self._lidar(root, frames, poses_file, align, source) if cfg.load_lidar else None
        tracks, key_to_track = self._tracks(root, n_full, frames, align, source)
        human = {}
        if cfg.load_human_poses and (root / "humanpose" / "smpl.pkl").is_file():
            human = self._human_poses(root, n_full, frames, align, source, per_frame, poses_file, key_to_track)
        for note in self.notes:
            warnings.warn(f"{root}: {note}", stacklevel=2)
        return self.build_scene(root.name, cameras, timestamps, frames, lidar=lidar, tracks=tracks, human_poses=human,
                                ego_poses=ego_poses)

    def _camera_ids(self, root: Path) -> list[int]:
        intr = root / "intrinsics"
        if not intr.is_dir():
            raise ProcessedSceneError(f"{intr}: missing")
        found = sorted(int(p.stem) for p in intr.glob("*.txt") if p.stem.isdigit())
        if not found:
            raise ProcessedSceneError(f"{intr}: no camera intrinsics files")
        if self.config.cameras:
            missing = [c for c in self.config.cameras if c not in found]
            if missing:
                raise ProcessedSceneError(f"{intr}: no intrinsics for cameras {missing} (found {found})")
            return list(self.config.cameras)
        return found

    def _extrinsics_layout(self, root: Path, cam: int) -> bool:
        ext = root / "extrinsics"
        if (ext / f"{cam}.txt").is_file():
            return False
        if (ext / f"000_{cam}.txt").is_file() or (ext / f"{self.config.start_frame:03d}_{cam}.txt").is_file():
            return True
        raise ProcessedSceneError(f"{ext}: neither {cam}.txt (per camera) nor 000_{cam}.txt (per frame) exists")

    def _detect_source(self, root: Path, pose_dir: Path, per_frame: bool, cam_ids: list[int],
                       poses: np.ndarray) -> str:
        if self.config.source != "auto":
            return self.config.source
        if per_frame:
            return "nuscenes" if pose_dir.name == "lidar_pose" else "pandaset"
        info = root / "instances" / "instances_info.json"
        if info.is_file():
            try:
                names = {v.get("class_name", "") for v in json.loads(info.read_text()).values()}
            except (ValueError, AttributeError):
                names = set()
            by_class = formats.detect_source_from_classes(names)
            if by_class in ("waymo", "argoverse", "nuplan", "kitti"):
                return by_class
        # Waymo camera axes: the camera's own z axis points up in the ego frame.
        E = _load_matrix(root / "extrinsics" / f"{cam_ids[0]}.txt")
        if E[2, 2] > 0.7:
            return "waymo"
        cols = self._lidar_columns(root)
        return {14: "waymo", 6: "nuplan", 5: "pandaset"}.get(cols or 0, "argoverse")

    def _lidar_columns(self, root: Path) -> Optional[int]:
        """Column count consistent with every LiDAR file size (preferring wider layouts)."""
        files = sorted((root / "lidar").glob("*.bin"))[:20]
        if not files:
            return None
        sizes = [f.stat().st_size for f in files]
        for cols in (14, 6, 5, 4):
            if all(s % (4 * cols) == 0 for s in sizes):
                return cols
        return None

    # ------------------------------------------------------------------ cameras
    def _cam_to_world_file(self, root: Path, cam: int, per_frame: bool, source: str,
                           poses: np.ndarray) -> np.ndarray:
        """(N, 4, 4) OpenCV camera->file-world for every frame of the log."""
        ext = root / "extrinsics"
        if per_frame:
            return np.stack([_load_matrix(ext / f"{t:03d}_{cam}.txt") for t in range(len(poses))])
        cam_to_ego = _load_matrix(ext / f"{cam}.txt")
        if source == "waymo":
            cam_to_ego = cam_to_ego @ WAYMO_TO_OPENCV
        return poses @ cam_to_ego

    def _camera(self, root: Path, cam: int, c2w_file: np.ndarray, align: np.ndarray, frames: np.ndarray,
                source: str) -> CameraSequence:
        path = root / "intrinsics" / f"{cam}.txt"
        try:
            vals = np.loadtxt(path, dtype=np.float64).reshape(-1)
        except ValueError as exc:
            raise ProcessedSceneError(f"{path}: not a list of numbers ({exc})") from None
        if vals.size != 9:
            raise ProcessedSceneError(f"{path}: expected 9 numbers (fx fy cx cy k1 k2 p1 p2 k3), found {vals.size}")
        fx, fy, cx, cy = vals[:4]
        # The reference keeps raw (distorted) images, e.g. Waymo's and NuPlan's: the core
        # undistorts images and masks to this pinhole K at load (omnire/data/images.py).
        distortion = vals[4:].copy() if np.any(vals[4:] != 0) else None
        if distortion is not None and not np.all(np.isfinite(distortion)):
            raise ProcessedSceneError(f"{path}: distortion k1 k2 p1 p2 k3 must be finite, got {distortion.tolist()}")
        images = [self._image_path(root / "images", f"{t:03d}_{cam}") for t in frames]
        centres = self.config.file_pixel_centres
        self.pixel_centres = formats.PIXEL_CENTRES[source] if centres == "auto" else centres
        K0 = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        names = formats.CAMERA_NAMES.get(source, ())
        name = names[cam] if cam < len(names) else f"camera_{cam}"
        sky = self._mask_paths(root / "sky_masks", cam, frames)
        dyn_root = root / "fine_dynamic_masks"
        if not (self.config.prefer_fine_masks and dyn_root.is_dir()):
            dyn_root = root / "dynamic_masks"
        dyn = {}
        for kind in ("all", "human", "vehicle"):
            paths = self._mask_paths(dyn_root / kind, cam, frames)
            if paths is not None:
                dyn[kind] = paths
        return loaded_camera(name, images, K0, image_size(images[0]), self.config.scale, self.pixel_centres,
                             distortion=distortion, cam_to_world=align @ c2w_file, timestamps=frames / self.config.fps,
                             sky_mask_paths=sky, dynamic_mask_paths=dyn or None)

    @staticmethod
    def _image_path(folder: Path, stem: str) -> Path:
        for ext in IMAGE_EXTS:
            p = folder / f"{stem}{ext}"
            if p.is_file():
                return p
        raise ProcessedSceneError(f"{folder / (stem + '.jpg')}: missing image")

    def _mask_paths(self, folder: Path, cam: int, frames: np.ndarray) -> Optional[list[Path]]:
        if not folder.is_dir():
            return None
        paths = [folder / f"{t:03d}_{cam}.png" for t in frames]
        missing = [p for p in paths if not p.is_file()]
        if missing:
            self.notes.append(f"{folder}: {len(missing)} of {len(paths)} masks missing for camera {cam}; not used")
            return None
        return paths

    # ------------------------------------------------------------------ lidar
    def _lidar(self, root: Path, frames: np.ndarray, poses: np.ndarray, align: np.ndarray,
               source: str) -> Optional[LidarSweeps]:
        folder = root / "lidar"
        if not folder.is_dir():
            return None
        layout = LIDAR_LAYOUTS[source]
        row = 4 * layout.columns
        points: list[Optional[np.ndarray]] = []
        intensity: list[Optional[np.ndarray]] = []
        origins = np.full((len(frames), 3), np.nan)
        for i, t in enumerate(frames):
            path = folder / f"{t:03d}.bin"
            if not path.is_file():
                points.append(None)
                intensity.append(None)
                continue
            size = path.stat().st_size
            if size % row:
                raise ProcessedSceneError(
                    f"{path}: {size} bytes is not a multiple of the {source} row size ({layout.columns} float32 "
                    f"columns = {row} bytes: {layout.description})"
                )
            data = np.fromfile(path, dtype=np.float32).reshape(-1, layout.columns)
            if source == "pandaset" and self.config.lidar_sensor_ids:
                data = data[np.isin(data[:, 4], self.config.lidar_sensor_ids)]
            xyz = data[:, layout.xyz:layout.xyz + 3].astype(np.float64)
            keep = np.isfinite(xyz).all(1)
            M = align @ poses[t]  # sensor/ego frame -> our world
            pts = xyz[keep] @ M[:3, :3].T + M[:3, 3]
            points.append(pts.astype(np.float32))
            if layout.intensity is not None:
                intensity.append(layout.intensity_scale.to_unit(
                    data[keep, layout.intensity], f"{path}: column {layout.intensity + 1} (intensity, {source} rows)",
                    ProcessedSceneError))
            if layout.origin is not None and len(data):
                o = data[:, layout.origin:layout.origin + 3].astype(np.float64).mean(0)
                origins[i] = M[:3, :3] @ o + M[:3, 3]
            else:
                origins[i] = M[:3, 3]
        return LidarSweeps(points, origins, intensity=intensity if layout.intensity is not None else None)

    # ------------------------------------------------------------------ tracks
    def _tracks(self, root: Path, n_full: int, frames: np.ndarray, align: np.ndarray,
                source: str) -> tuple[list[ActorTrack], dict[str, str]]:
        path = root / "instances" / "instances_info.json"
        if not path.is_file():
            return [], {}
        try:
            info = json.loads(path.read_text())
        except ValueError as exc:
            raise ProcessedSceneError(f"{path}: invalid JSON ({exc})") from None
        if not isinstance(info, dict):
            raise ProcessedSceneError(f"{path}: expected an object of instances, got {type(info).__name__}")
        # Pass 1: every instance over the whole log, as written (the heading axis is a
        # property of the file, decided from all of it whatever range is loaded).
        parsed, unknown = [], set()
        for key, inst in info.items():
            where = f"{path}: instance {key!r}"
            try:
                ann = inst["frame_annotations"]
                fidx, o2w, sizes = ann["frame_idx"], ann["obj_to_world"], ann["box_size"]
                class_name = str(inst["class_name"])
            except (KeyError, TypeError) as exc:
                raise ProcessedSceneError(f"{where}: missing field {exc}") from None
            if not (len(fidx) == len(o2w) == len(sizes)):
                raise ProcessedSceneError(f"{where}: frame_idx, obj_to_world and box_size lengths differ")
            bad = [int(t) for t in fidx if not 0 <= int(t) < n_full]
            if bad:
                raise ProcessedSceneError(
                    f"{where}: frame_idx {bad[:5]} outside the log (0..{n_full - 1}, from ego_pose/)"
                )
            try:
                o2w = np.asarray(o2w, dtype=np.float64).reshape(len(fidx), 4, 4)
                sizes = np.asarray(sizes, dtype=np.float64).reshape(len(fidx), 3)
            except ValueError:
                raise ProcessedSceneError(
                    f"{where}: obj_to_world must be 4x4 matrices and box_size 3 numbers per frame"
                ) from None
            if not (np.isfinite(o2w).all() and np.isfinite(sizes).all()):
                raise ProcessedSceneError(f"{where}: obj_to_world or box_size holds NaN or inf")
            fidx = np.asarray(fidx, dtype=np.int64)
            order = np.argsort(fidx, kind="stable")
            category = category_of(class_name, source)
            if category is None:
                unknown.add(class_name)
                category = "other"
            flags = ann.get("stationary")
            flags = np.asarray(flags, dtype=bool)[order] if flags is not None and len(flags) == len(fidx) else None
            parsed.append((key, inst, class_name, category, fidx[order], o2w[order], sizes[order], flags))
        if unknown:
            self.notes.append(f"unknown class names {sorted(unknown)} mapped to category 'other'")
        k = self._heading_axis(parsed, source, path)

        # Pass 2: the loaded frames, in the world, x along the heading.
        fix = np.eye(4)
        fix[:3, :3] = boxes.axis_fix(k)
        F = len(frames)
        local = np.full(n_full, -1)
        local[frames] = np.arange(F)
        tracks, key_to_track = [], {}
        for key, inst, class_name, category, fidx, o2w, sizes, flags in parsed:
            i = local[fidx]
            sel = i >= 0
            if not sel.any():
                continue
            poses = np.tile(np.eye(4), (F, 1, 1))
            present = np.zeros(F, bool)
            poses[i[sel]] = align @ o2w[sel] @ fix
            present[i[sel]] = True
            size = boxes.size_fix(sizes[sel], k).max(0)
            if flags is not None:  # the dataset's own per-frame flag (PandaSet)
                stationary = bool(flags[sel].all())
            else:
                stationary = is_stationary(poses[present, :3, 3], self.config.stationary_threshold)
            track_id = str(inst.get("id", key))
            tracks.append(ActorTrack(track_id, class_name, category, poses, size, present, stationary=stationary))
            key_to_track[str(key)] = track_id
        fi_path = root / "instances" / "frame_instances.json"
        if fi_path.is_file():
            try:
                fi = json.loads(fi_path.read_text())
            except ValueError as exc:
                raise ProcessedSceneError(f"{fi_path}: invalid JSON ({exc})") from None
            for t, ids in fi.items():
                if not 0 <= int(t) < n_full:
                    raise ProcessedSceneError(f"{fi_path}: frame {t} outside the log (0..{n_full - 1})")
                missing = [i for i in ids if str(i) not in info]
                if missing:
                    raise ProcessedSceneError(f"{fi_path}: frame {t} lists instances {missing[:5]} not in instances_info.json")
        return tracks, key_to_track

    def _heading_axis(self, parsed: list, source: str, path: Path) -> int:
        """Index k (``boxes.AXES``) of the local axis of the file's boxes along the heading."""
        if self.config.box_heading_axis != "auto":
            self.heading_axis = boxes.HeadingAxis(boxes.AXES.index(self.config.box_heading_axis), "configured",
                                                  np.zeros(4), np.zeros(2))
            return self.heading_axis.k
        if not parsed:
            self.heading_axis = None
            return boxes.AXES.index(formats.BOX_HEADING_AXIS[source])
        found = boxes.detect_heading_axis([(p[4], p[5], p[6], p[3]) for p in parsed],
                                          formats.BOX_HEADING_AXIS[source], source)
        self.heading_axis = found
        if found.warning:
            self.notes.append(f"{path.name}: {found.warning}")
        return found.k

    # ------------------------------------------------------------------ humans
    def _human_poses(self, root: Path, n_full: int, frames: np.ndarray, align: np.ndarray, source: str,
                     per_frame: bool, poses: np.ndarray, key_to_track: dict[str, str]) -> dict[str, HumanPoseSequence]:
        from omnire_processed.pickles import load_smpl_pickle

        path = root / "humanpose" / "smpl.pkl"
        data = load_smpl_pickle(path)
        if not isinstance(data, dict):
            raise ProcessedSceneError(f"{path}: expected a dict of instances, got {type(data).__name__}")
        c2w_cache: dict[int, np.ndarray] = {}

        def cam_rot(cam: int) -> np.ndarray:  # (N, 3, 3) camera->our-world rotations
            if cam not in c2w_cache:
                c2w_cache[cam] = (align @ self._cam_to_world_file(root, cam, per_frame, source, poses))[:, :3, :3]
            return c2w_cache[cam]

        out = {}
        F = len(frames)
        for key, entry in data.items():
            track = key_to_track.get(str(key))
            if track is None:
                continue  # a pedestrian outside the loaded range (or unknown instance)
            where = f"{path}: instance {key!r}"
            try:
                smpl = entry["smpl"]
                go = _to_numpy(smpl["global_orient"]).astype(np.float64).reshape(-1, 3, 3)
                bp = _to_numpy(smpl["body_pose"]).astype(np.float64)
                betas = _to_numpy(smpl.get("betas", np.zeros((len(go), 0)))).astype(np.float64)
                valid = _to_numpy(entry["valid_mask"]).astype(bool).reshape(-1)
                cams = _to_numpy(entry["selected_cam_idx"]).astype(np.int64).reshape(-1)
            except (KeyError, TypeError) as exc:
                raise ProcessedSceneError(f"{where}: missing field {exc}") from None
            if bp.shape[1:] != (23, 3, 3):
                raise ProcessedSceneError(f"{where}: body_pose has shape {bp.shape}, expected (F, 23, 3, 3)")
            if not (len(go) == len(bp) == len(valid) == len(cams)) or len(go) < frames[-1] + 1:
                raise ProcessedSceneError(
                    f"{where}: pose arrays have {len(go)}/{len(bp)}/{len(valid)}/{len(cams)} frames, "
                    f"need {frames[-1] + 1}"
                )
            go_w = np.tile(np.eye(3), (F, 1, 1))
            body = np.tile(np.eye(3), (F, 23, 1, 1))
            ok = np.zeros(F, bool)
            for i, t in enumerate(frames):
                if not valid[t]:
                    continue
                try:
                    R = cam_rot(int(cams[t]))[t]
                except ProcessedSceneError as exc:
                    raise ProcessedSceneError(f"{where}: selected camera {cams[t]} at frame {t}: {exc}") from None
                go_w[i] = R @ go[t]
                body[i] = bp[t]
                ok[i] = True
            if not ok.any():
                continue
            # Frames without an estimate hold the nearest valid frame (flagged invalid).
            vidx = np.flatnonzero(ok)
            nearest = vidx[np.abs(np.arange(F)[:, None] - vidx[None]).argmin(1)]
            go_w, body = go_w[nearest], body[nearest]
            b = betas[frames][ok].mean(0) if betas.ndim == 2 and betas.shape[0] >= frames[-1] + 1 else np.zeros(0)
            out[track] = HumanPoseSequence(track, go_w, body, b, ok, source="smpl.pkl")
        return out
