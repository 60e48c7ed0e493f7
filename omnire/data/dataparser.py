"""Base config and class for dataparsers (dataset readers)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from omnire.config import InstantiateConfig
from omnire.data.scene import SceneData


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
    """Pixels showing the recording vehicle, left out of losses and metrics: "dataset" (the
    reader's own masks, if it has any), "auto" (estimated from the images where the reader
    has none), "none", or a folder holding <camera name>.png per camera (non-zero = vehicle)."""


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


@dataclasses.dataclass
class LogDataparserConfig(DataparserConfig):
    """Fields of readers of a recorded log: camera and frame selection, LiDAR on/off."""

    cameras: tuple[str, ...] = ()
    """Cameras to load by the dataset's names (empty: the reader's default set)."""
    start_frame: int = 0
    """First frame of the log to load (0-based)."""
    end_frame: int = -1
    """One past the last frame to load; -1 loads to the end of the log."""
    load_lidar: bool = True
    """Load LiDAR (used for initialisation and the depth loss)."""
