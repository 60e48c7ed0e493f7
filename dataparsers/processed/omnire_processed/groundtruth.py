"""A synthetic scene (``omnire synth``, processed layout) as scene writers see it: the
processed reader's :class:`SceneData` plus the generator's ground truth
(``ground_truth.npz`` / ``.json`` beside the scene), all in the generator world (z up, metres).

It lives with the processed reader, which it is built on, so that the dataset distributions
whose scene writers convert synthetic scenes (kitti, nuscenes, ...) depend on the processed
reader only, never on the generator (``omnire-dataparser-synthetic``) that calls them."""
from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

from omnire.api import SceneData, SceneDataError, atomic_write_bytes, atomic_write_text
from omnire_processed.reader import ProcessedDataparser, ProcessedDataparserConfig


@dataclasses.dataclass
class SyntheticSource:
    """Attributes (F frames, C cameras, N actors; poses in the generator world):
        scene: the processed reader's scene (its own world; use ``gen_from_scene``).
        gen_from_scene: (4, 4) processed-reader world -> generator world.
        times: (F,) seconds from 0. ego: (F, 4, 4) ego-to-world (x forward, y left, z up).
        cam_to_ego: (C, 4, 4) OpenCV camera -> ego. K: (C, 3, 3), pixel centres at +0.5.
        lidar_to_ego: (4, 4) LiDAR position on the car (axes of the ego).
        track_ids, kinds: (N,) str; boxes: (N, F, 4, 4) written box-to-world (x along the
        heading); sizes: (N, 3) length, width, height; present: (N, F) bool; stationary: (N,).
        intensity: F arrays (N_t,) in [0, 1] matching the points, or None.
        meta: ground_truth.json.
    """

    source: Path
    scene: SceneData
    gen_from_scene: np.ndarray
    times: np.ndarray
    ego: np.ndarray
    cam_to_ego: np.ndarray
    K: np.ndarray
    lidar_to_ego: np.ndarray
    track_ids: np.ndarray
    kinds: np.ndarray
    boxes: np.ndarray
    sizes: np.ndarray
    present: np.ndarray
    stationary: np.ndarray
    intensity: list[Optional[np.ndarray]]
    meta: dict
    ground_truth: dict

    @property
    def num_frames(self) -> int:
        return len(self.times)

    def points(self, t: int) -> np.ndarray:
        """(N, 3) float64 LiDAR points of frame ``t`` in the generator world."""
        p = self.scene.lidar.points[t].astype(np.float64)
        M = self.gen_from_scene
        return p @ M[:3, :3].T + M[:3, 3]

    @classmethod
    def load(cls, source: Path) -> "SyntheticSource":
        source = Path(source)
        for name in ("ground_truth.npz", "ground_truth.json"):
            if not (source / name).is_file():
                raise SceneDataError(f"{source / name}: missing; the scene writer converts scenes written by "
                                     "`omnire synth` (processed layout with ground truth)")
        reader = ProcessedDataparser(ProcessedDataparserConfig(data=source, scale=1.0, holdout_every=0,
                                                               load_human_poses=False))
        with warnings.catch_warnings():  # notes about the processed files' conventions: boxes come from the ground truth
            warnings.simplefilter("ignore")
            scene = reader.parse()
        with np.load(source / "ground_truth.npz") as z:
            gt = {k: z[k] for k in z.files}
        meta = json.loads((source / "ground_truth.json").read_text())
        G = gt["file_from_generator"]
        gen_from_scene = np.linalg.inv(reader.world_from_file @ G)
        ego = gt["ego_to_world"]
        F = len(gt["timestamps"])
        if scene.lidar is None or any(p is None for p in scene.lidar.points):
            raise SceneDataError(f"{source / 'lidar'}: the synthetic scene lacks LiDAR frames")
        # The sensor sits at a fixed place on the car: its origin in the ego frame.
        o = scene.lidar.origins @ gen_from_scene[:3, :3].T + gen_from_scene[:3, 3]  # (F, 3) generator world
        offsets = np.stack([np.linalg.inv(ego[t]) @ np.append(o[t], 1.0) for t in range(F)])[:, :3]
        lidar_to_ego = np.eye(4)
        lidar_to_ego[:3, 3] = np.median(offsets, axis=0)
        intensity = scene.lidar.intensity or [None] * F  # in [0, 1]: the reader maps the files' scale
        return cls(
            source=source, scene=scene, gen_from_scene=gen_from_scene, times=gt["timestamps"].astype(np.float64),
            ego=ego, cam_to_ego=gt["cam_to_ego"], K=gt["intrinsics"], lidar_to_ego=lidar_to_ego,
            track_ids=gt["track_ids"], kinds=gt["track_kinds"], boxes=gt["box_poses_written"],
            sizes=gt["box_sizes"], present=gt["present"].astype(bool), stationary=gt["stationary"].astype(bool),
            intensity=intensity, meta=meta, ground_truth=gt,
        )

    def save_ground_truth(self, output: Path, file_from_generator: np.ndarray, note: str) -> None:
        """Ground truth beside a converted scene (not part of the dataset's layout; readers
        ignore it): the generator's arrays with ``file_from_generator`` of the new layout."""
        import io

        arrays = dict(self.ground_truth)
        arrays["file_from_generator"] = file_from_generator
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        atomic_write_bytes(output / "ground_truth.npz", buf.getvalue())
        meta = dict(self.meta)
        meta["converted"] = note
        atomic_write_text(output / "ground_truth.json", json.dumps(meta, indent=1))

