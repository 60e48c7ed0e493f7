"""Base configs and class for dataparsers (dataset readers), and what every reader does the
same way: option checks, frame selection, the sample nearest in time, the world anchor, camera
sizes and intrinsics at the loaded scale, tracks resampled to the frames, the stationary test,
the scene's hold-out split.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Literal, Optional, Sequence

import numpy as np
import tyro

from omnire.config import InstantiateConfig
from omnire.data.scene import CameraSequence, SceneData, holdout_split

STATIONARY_THRESHOLD = 0.5
"""Default of ``stationary_threshold`` (m) in every reader; see :func:`is_stationary` and
docs/datasets.md (Shared options) for why 0.5."""

MaxTrackGap = Annotated[float, tyro.conf.arg(aliases=("--max-box-gap",))]
"""Type of ``max_track_gap`` in the KITTI and nuScenes readers, which called the option
``--max-box-gap`` before: the old spelling stays accepted so that the recorded command lines
of their runs (run.json ``argv``) still load. Other readers declare a plain float."""


@dataclasses.dataclass
class DataparserConfig(InstantiateConfig):
    """Fields every dataparser shares. Subclasses add dataset-specific ones."""

    data: Path = Path(".")
    """Scene directory."""
    scale: float = 0.5
    """Image scale relative to the files on disk (intrinsics are scaled to match)."""
    holdout_every: int = 10
    """Hold out every N-th frame (all cameras) for novel-view evaluation; 0 holds out none."""
    ego_masks: str = "dataset"
    """Pixels showing the recording vehicle, left out of losses and metrics: "dataset" uses the reader's own masks (if it has any), "auto" estimates them from the images where the reader has none, "none" uses none, and a folder holding <camera name>.png per camera (non-zero = vehicle) uses those."""

    def check(self) -> None:
        """Raise :class:`~omnire.errors.ConfigError` naming the first invalid shared field.
        Readers call it first in ``parse`` and check their own fields after it."""
        from omnire.errors import ConfigError

        if not self.scale > 0:
            raise ConfigError(f"scale: {self.scale}, expected a positive number")


@dataclasses.dataclass
class LogDataparserConfig(DataparserConfig):
    """Fields of readers of a recorded log: camera and frame selection, LiDAR on/off and
    thinning, tracks interpolated across unannotated frames, the stationary test."""

    cameras: tuple[str, ...] = ()
    """Cameras to load by the dataset's names (empty: the reader's default set)."""
    start_frame: int = 0
    """First frame of the log to load (0-based)."""
    end_frame: int = -1
    """One past the last frame to load; -1 loads to the end of the log."""
    load_lidar: bool = True
    """Load LiDAR (used for initialisation and the depth loss)."""
    max_lidar_points_per_frame: int = 0
    """Randomly thin each sweep to at most this many points (the same points whatever frames are loaded); 0 keeps all."""
    max_track_gap: float = 1.0
    """Interpolate a track across unannotated frames when the annotations around them are at most this many seconds apart; across longer gaps the actor is absent. 0 keeps the annotated frames only."""
    stationary_threshold: float = STATIONARY_THRESHOLD
    """A track is stationary when the medians of its box centres over the first and last thirds of its loaded frames are less than this many metres apart."""

    def check(self) -> None:
        from omnire.errors import ConfigError

        super().check()
        if self.max_lidar_points_per_frame < 0:
            raise ConfigError(f"max_lidar_points_per_frame: {self.max_lidar_points_per_frame}, expected >= 0 "
                              "(0 keeps all)")
        if not self.max_track_gap >= 0:
            raise ConfigError(f"max_track_gap: {self.max_track_gap}, expected >= 0 seconds")
        if not self.stationary_threshold >= 0:
            raise ConfigError(f"stationary_threshold: {self.stationary_threshold}, expected >= 0 metres")
        if len(set(self.cameras)) != len(self.cameras):
            raise ConfigError(f"cameras: {list(self.cameras)} lists a camera twice")


class Dataparser:
    """Reads one scene. Subclasses implement :meth:`parse`; callers use :meth:`load`."""

    def __init__(self, config: DataparserConfig) -> None:
        self.config = config

    def parse(self) -> SceneData:
        raise NotImplementedError

    def load(self) -> SceneData:
        """:meth:`parse`, then the ego-mask choice of the config applied, then validated."""
        scene = self.parse()
        apply_ego_mask_choice(scene, self.config.ego_masks)
        return scene.validate()

    def build_scene(self, name: str, cameras: list, frame_timestamps: np.ndarray, source_frames: np.ndarray,
              **fields) -> SceneData:
        """The validated :class:`SceneData` of the loaded frames, split for evaluation by the
        config's ``holdout_every``; ``fields`` are SceneData's other fields (lidar, tracks,
        ego_poses, attribution, ...)."""
        train, test = holdout_split(len(frame_timestamps), self.config.holdout_every)
        return SceneData(name=name, cameras=cameras, frame_timestamps=frame_timestamps, source_frames=source_frames,
                         train_frames=train, test_frames=test, **fields).validate()


def apply_ego_mask_choice(scene: SceneData, choice: str) -> None:
    """Set each camera's ego mask per ``choice`` (see :attr:`DataparserConfig.ego_masks`)."""
    from omnire.errors import ConfigError, MissingFileError

    if choice == "dataset":
        return
    if choice == "none":
        for cam in scene.cameras:
            cam.ego_mask_path = None
        return
    if choice == "auto":
        scene.estimate_ego_masks = True
        return
    folder = Path(choice)
    if not folder.is_dir():
        raise ConfigError(f"--ego-masks {choice!r}: expected dataset, auto, none, or a folder of <camera>.png masks")
    for cam in scene.cameras:
        path = folder / f"{cam.name}.png"
        if not path.is_file():
            raise MissingFileError(f"{path}: no ego mask for camera {cam.name} in --ego-masks {folder}")
        cam.ego_mask_path = path


def frame_range(start: int, end: int, total: int, source: str) -> range:
    """Frames ``start`` .. ``end`` - 1 of a log with ``total`` frames (``end`` = -1: to the
    end). Raises :class:`~omnire.errors.ConfigError` naming ``source`` for an empty or
    out-of-range selection."""
    from omnire.errors import ConfigError

    stop = total if end < 0 else end
    if not 0 <= start < stop <= total:
        raise ConfigError(f"{source}: frames {start}..{end} (--start-frame/--end-frame) select nothing of the "
                          f"{total} frames of the log (valid: 0 <= start < end <= {total}, end -1 = to the end)")
    return range(start, stop)


def first_pose_world(ego_to_source: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a dataset's world frame to the omnire world: origin at the ego
    pose ``ego_to_source`` (4, 4) (the first loaded one), x along its heading projected on
    the ground, z kept up (the ego's roll and pitch are not undone, docs/conventions.md "World frame")."""
    from omnire.geometry import rot_z

    forward = ego_to_source[:3, 0]
    yaw = float(np.arctan2(forward[1], forward[0]))
    world_to_source = np.eye(4)
    world_to_source[:3, :3] = rot_z(np.array(yaw))
    world_to_source[:3, 3] = ego_to_source[:3, 3]
    return np.linalg.inv(world_to_source)


def nearest_index(times: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Index (Q,) into increasing ``times`` (N,), N >= 1, of the value nearest each of
    ``query`` (Q,) (same unit); a tie takes the earlier one. Readers pick, per frame, the
    image or sweep nearest in time with it."""
    times, query = np.asarray(times), np.asarray(query)
    if len(times) == 1:
        return np.zeros(len(query), dtype=np.int64)
    i = np.searchsorted(times, query).clip(1, len(times) - 1)
    earlier = np.abs(query - times[i - 1]) <= np.abs(times[i] - query)
    return np.where(earlier, i - 1, i)


def require_files(paths: Sequence[Path], what: str, error: Optional[type] = None) -> None:
    """Raise ``error`` (default :class:`~omnire.errors.MissingFileError`) naming the first of
    ``paths`` that is not a file, ``what`` it is, and how many more are missing."""
    from omnire.errors import MissingFileError

    missing = [p for p in paths if not Path(p).is_file()]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise (error or MissingFileError)(f"{missing[0]}: missing {what}{more}")


def loaded_intrinsics(K: np.ndarray, width: int, height: int, scale: float,
                      pixel_centres: Literal["half", "integer"] = "half") -> tuple[int, int, np.ndarray]:
    """A pinhole camera of ``width`` x ``height`` px on disk with K (3, 3) -> (width, height,
    K (3, 3)) at the loaded size: each side times ``scale``, rounded, at least 1 px; K scaled
    per axis by the exact ratio of the sizes.

    ``pixel_centres`` is the convention of the given K: "half" centres pixel (i, j) at
    (i + 0.5, j + 0.5), as omnire does (the image spans [0, W] x [0, H]); "integer" centres it
    at (i, j), as OpenCV does, so the principal point first moves by +0.5 px. In omnire's
    convention resizing is a plain multiplication.
    """
    K = np.asarray(K, dtype=np.float64)
    w_out, h_out = max(1, round(width * scale)), max(1, round(height * scale))
    sx, sy = w_out / width, h_out / height
    shift = {"half": 0.0, "integer": 0.5}[pixel_centres]
    out = np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + shift) * sx],
                    [0.0, K[1, 1] * sy, (K[1, 2] + shift) * sy],
                    [0.0, 0.0, 1.0]])
    return w_out, h_out, out


def loaded_camera(name: str, image_paths: Sequence[Path], K: np.ndarray, size: tuple[int, int], scale: float,
                  pixel_centres: Literal["half", "integer"] = "half", **fields) -> CameraSequence:
    """The :class:`~omnire.data.scene.CameraSequence` of camera ``name`` whose images
    ``image_paths`` are ``size`` (width, height) px on disk with K (3, 3) in the
    ``pixel_centres`` convention, loaded at ``scale`` (:func:`loaded_intrinsics`); ``fields``
    are its other fields (cam_to_world, timestamps, distortion, masks, extras)."""
    width, height, K = loaded_intrinsics(K, size[0], size[1], scale, pixel_centres)
    return CameraSequence(name=name, width=width, height=height, intrinsics=K, image_paths=list(image_paths), **fields)


def hold_absent_poses(poses: np.ndarray, present: np.ndarray) -> np.ndarray:
    """(F, 4, 4) poses, (F,) present -> the poses with each absent row replaced by the nearest
    earlier present one (rows before the first present one take it), so that the rows
    :class:`~omnire.data.scene.ActorTrack` leaves unspecified are finite poses. Unchanged when
    nothing is present."""
    present = np.asarray(present, bool)
    if not present.any():
        return poses
    F = len(present)
    last = np.maximum.accumulate(np.where(present, np.arange(F), -1))
    last[last < 0] = int(np.flatnonzero(present)[0])
    return poses[last]


def resample_track(times: np.ndarray, boxes: np.ndarray, query: np.ndarray,
                   max_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (K, 4, 4) annotated at increasing ``times`` (K,) -> (poses (Q, 4, 4), present (Q,))
    at the ``query`` times (Q,), same unit: the annotation itself at an annotated time,
    interpolated (:func:`~omnire.interpolation.interpolate_track`: SLERP and linear) between
    annotations at most ``max_gap`` apart, absent elsewhere; absent rows as
    :func:`hold_absent_poses` leaves them."""
    from omnire.interpolation import interpolate_track

    poses, present = interpolate_track(times, boxes, np.ones(len(times), bool), query, max_gap=max(max_gap, 0.0))
    return hold_absent_poses(poses, present), present


def is_stationary(centres: np.ndarray, threshold: float = STATIONARY_THRESHOLD) -> bool:
    """True when the box centres (K, 3) of a track's present frames, in time order, move less
    than ``threshold`` metres net: the distance between the medians of the first and the last
    third. Medians, not the farthest excursion, because annotated boxes jitter by tenths of a
    metre from frame to frame and a parked car must stay parked."""
    centres = np.asarray(centres, dtype=np.float64)
    if len(centres) < 2:
        return True
    n = max(1, len(centres) // 3)
    return bool(np.linalg.norm(np.median(centres[-n:], 0) - np.median(centres[:n], 0)) < threshold)


def majority_label(labels: Sequence[str]) -> str:
    """The most frequent of a track's per-frame labels; a tie goes to the alphabetically first."""
    names, counts = np.unique(np.asarray([str(v) for v in labels]), return_counts=True)
    return str(names[np.argmax(counts)])
