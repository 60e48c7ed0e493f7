"""PandaSet reader: one sequence in PandaSet's own on-disk layout -> :class:`SceneData`.

Layout read (one sequence directory, frames numbered ``00``, ``01``, ...)::

    camera/<cam>/NN.jpg, intrinsics.json {fx, fy, cx, cy}, poses.json, timestamps.json
    lidar/NN.pkl.gz          pandas DataFrame x, y, z (PandaSet world), i, t, d (sensor id)
    lidar/poses.json, timestamps.json      Pandar64 pose / time per frame (the frame clock)
    annotations/cuboids/NN.pkl.gz          pandas DataFrame of boxes (PandaSet world)
    meta/source_frames.json  optional (written by tools/make_demo_cut.py): original frame
                             numbers of a cut, reported as ``SceneData.source_frames``

Conventions verified on sequence 002 (see the tests and the package README):

- PandaSet's world frame is z up, metres, with an arbitrary origin and heading. Its LiDAR
  poses use the Hesai sensor axes x right, y forward, z up: over frames 40-79 the ego
  drives along world +45 degrees while the pose's y axis points along +45 and its x axis
  along -45 degrees. The omnire world is PandaSet's world translated to the first loaded
  LiDAR position and rotated about z by the heading (the pose's y axis), so world x points
  along the ego heading and z stays exactly up (the sensor's small roll/pitch is not undone).
- Camera poses are OpenCV camera-to-world already (p_cam = R^T (p_world - t) projects box
  centres onto the cars), so only the world change is applied.
- Intrinsics centre pixel (i, j) at (i + 0.5, j + 0.5), like omnire (pandaset-devkit's
  ``geometry.projection`` treats the image as 0 < u < width, 0 < v < height): used as is.
- Cuboid ``yaw`` rotates a box frame whose x axis is the *width* (dimensions.x) and y axis
  the length (dimensions.y): moving objects travel along yaw + 90 degrees (median error
  under 0.5 degrees on 002). omnire boxes put x along the heading, so the box rotation is
  Rz(yaw + pi/2) and size = (dimensions.y, dimensions.x, dimensions.z).
"""
from __future__ import annotations

import dataclasses
import json
import math
import pickle
import zlib
from pathlib import Path
from typing import Any, Optional, Sequence, Type

import numpy as np
import pandas as pd

from omnire.api import (
    BYTE_INTENSITY,
    ActorTrack,
    CameraSequence,
    Dataparser,
    DataparserConfig,
    LidarSweeps,
    MissingFileError,
    SceneData,
    SceneDataError,
    holdout_split,
    image_size,
    quat_to_rotmat,
    rot_z,
    safe_pickle,
)
from omnire.api import hold_absent_poses, loaded_camera, require_files, thin_points

from omnire_pandaset import pandar64

CAMERAS = (
    "front_camera",
    "front_left_camera",
    "front_right_camera",
    "left_camera",
    "right_camera",
    "back_camera",
)
"""The six PandaSet cameras (PandaSet camera ids 0..5 in this order)."""

EGO_MASKS = {
    name: path for name in CAMERAS
    if (path := Path(__file__).resolve().parent / "assets" / "ego_masks" / f"{name}.png").is_file()
}
"""Masks of the recording car's own body per camera (same car, so the same for every log):
the back camera sees the trunk in the lower sixth of its image. Estimated from log 002 with
omnire.egomask and checked by eye."""

LIDAR_SENSORS = {0: "Pandar64 (360-degree)", 1: "PandarGT (forward-facing)"}
"""PandaSet LiDAR sensor ids (column ``d`` of the point clouds, ``cuboids.sensor_id``)."""

ATTRIBUTION = (
    '"PandaSet: Advanced Sensor Suite Dataset for Autonomous Driving", Xiao et al., ITSC 2021, '
    "CC BY 4.0 (Scale AI and Hesai; PandaSet Dataset Terms of Use)."
)

_VEHICLE = frozenset(
    {
        "Car",
        "Pickup Truck",
        "Medium-sized Truck",
        "Semi-truck",
        "Bus",
        "Construction Vehicle",
        "Emergency Vehicle",
        "Towed Object",
        "Train",
    }
)
_HUMAN = frozenset({"Pedestrian", "Pedestrian with Object"})
_CYCLIST = frozenset({"Bicycle", "Motorcycle", "Personal Mobility Device", "Motorized Scooter"})

# Pandar64 sensor axes (x right, y forward, z up) -> ego axes (x forward, y left, z up):
# columns are the ego axes written in sensor coordinates. ego_to_world = lidar_to_world @ this.
_EGO_IN_LIDAR = np.array(
    [[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
_CUBOID_COLUMNS = ("uuid", "label", "yaw", "position.x", "position.y", "position.z",
                   "dimensions.x", "dimensions.y", "dimensions.z")


def category_of(label: str) -> str:
    """PandaSet class label -> omnire actor category (vehicle, human, cyclist, other)."""
    if label in _VEHICLE or label.startswith("Other Vehicle"):
        return "vehicle"
    if label in _HUMAN:
        return "human"
    if label in _CYCLIST:
        return "cyclist"
    return "other"  # cones, signs, animals, debris, ...


# ----------------------------------------------------------------------------- geometry
def world_change(lidar_to_world: np.ndarray) -> np.ndarray:
    """(4, 4) PandaSet-world -> omnire-world transform anchored at one LiDAR pose.

    Origin at the sensor position; rotated about z only, by the yaw of the sensor's y axis
    (its forward axis), so omnire x = ego heading and z stays PandaSet's (gravity) up.
    """
    forward = lidar_to_world[:3, 1]
    yaw = math.atan2(forward[1], forward[0])
    anchor = np.eye(4)
    anchor[:3, :3] = rot_z(np.float64(yaw))
    anchor[:3, 3] = lidar_to_world[:3, 3]
    return np.linalg.inv(anchor)


def _pose_matrices(entries: list[Any], path: Path) -> np.ndarray:
    """PandaSet poses.json entries -> (N, 4, 4) matrices."""
    try:
        t = np.array([[e["position"][k] for k in "xyz"] for e in entries], dtype=np.float64)
        q = np.array([[e["heading"][k] for k in "wxyz"] for e in entries], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneDataError(
            f"{path}: malformed pose entry ({type(exc).__name__}: {exc}); expected a list of "
            '{"position": {"x", "y", "z"}, "heading": {"w", "x", "y", "z"}}'
        ) from None
    if not (np.isfinite(t).all() and np.isfinite(q).all()) or (np.linalg.norm(q, axis=1) < 1e-8).any():
        raise SceneDataError(f"{path}: non-finite position or zero/non-finite heading quaternion")
    out = np.tile(np.eye(4), (len(entries), 1, 1))
    out[:, :3, :3] = quat_to_rotmat(q)
    out[:, :3, 3] = t
    return out


# ----------------------------------------------------------------------------- file reading
def _read_json(path: Path, what: str) -> Any:
    if not path.is_file():
        raise MissingFileError(f"{path}: missing {what}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneDataError(f"{path}: not valid JSON ({exc}); expected {what}") from None


def _read_json_list(path: Path, length: int, what: str) -> list[Any]:
    data = _read_json(path, what)
    if not isinstance(data, list) or len(data) != length:
        got = f"{len(data)} entries" if isinstance(data, list) else type(data).__name__
        raise SceneDataError(
            f"{path}: {got}, expected a list of {length} entries ({what}, one per frame of the "
            f"log as counted by lidar/timestamps.json)"
        )
    return data


PANDAS_FRAMES = safe_pickle.NUMPY_DATA | safe_pickle.PickleAllowlist(frozenset({
    ("pandas", "DataFrame"),
    ("pandas", "Index"),
    ("pandas", "RangeIndex"),
    ("pandas", "Series"),
    ("pandas._libs.internals", "_unpickle_block"),
    ("pandas.core.frame", "DataFrame"),
    ("pandas.core.series", "Series"),
    ("pandas.core.indexes.base", "Index"),
    ("pandas.core.indexes.base", "_new_Index"),
    ("pandas.core.indexes.range", "RangeIndex"),
    ("pandas.core.internals.managers", "BlockManager"),
    ("pandas.core.internals.managers", "SingleBlockManager"),
    ("pandas.core.internals.blocks", "new_block"),
}))
"""What a PandaSet ``*.pkl.gz`` may hold: a pandas DataFrame of numpy columns."""
FRAME_TABLE_MAX_BYTES = 256 * 2**20
"""A PandaSet frame table unpickled: LiDAR sweeps are ~10 MB (170k points x 6 columns), cuboid
tables far less; anything over 256 MB is not a PandaSet frame."""


def load_frame_table(path: Path) -> Any:
    """A PandaSet ``*.pkl.gz`` through the restricted unpickler (pandas DataFrames only)."""
    return safe_pickle.load(path, PANDAS_FRAMES, FRAME_TABLE_MAX_BYTES)


def _read_frame_table(path: Path, columns: Sequence[str], what: str) -> pd.DataFrame:
    """Load a PandaSet ``*.pkl.gz`` through the restricted unpickler; check the columns."""
    expected = f"a gzip-compressed pickle of a pandas DataFrame with columns {', '.join(columns)}"
    try:
        table = load_frame_table(path)
    except FileNotFoundError:
        raise MissingFileError(f"{path}: missing {what}") from None
    except (pickle.UnpicklingError, EOFError, OSError, zlib.error) as exc:
        raise SceneDataError(f"{path}: unreadable {what} ({exc}); expected {expected}") from None
    if not isinstance(table, pd.DataFrame):
        raise SceneDataError(f"{path}: holds a {type(table).__name__}, expected {expected}")
    missing = [c for c in columns if c not in table.columns]
    if missing:
        raise SceneDataError(f"{path}: {what} lacks columns {missing}; expected {expected}")
    return table


def _frame_file(directory: Path, frame: int, suffix: str) -> Path:
    return directory / f"{frame:02d}{suffix}"


# ----------------------------------------------------------------------------- cuboids
def deduplicate_cuboids(frames: Sequence[pd.DataFrame]) -> list[pd.DataFrame]:
    """One row per physical object and frame, with a stable ``track_id`` column added.

    PandaSet annotates its two LiDARs separately: an object outside their overlap has one
    row with ``cuboids.sensor_id == -1``; inside the overlap it may have one row per sensor
    (0 = Pandar64, 1 = PandarGT), each with its own uuid, linked by ``cuboids.sibling_id``
    (= the other row's uuid; ``-`` when none). The link is stable over time, so uuids joined
    by sibling links over all given frames are one object. Its track id is the uuid of the
    360-degree Pandar64 (or merged) rows, which see it longest; ties go to the uuid with
    more rows, then the smaller uuid. In each frame the row of that uuid is kept, otherwise
    the other sensor's row (so a track continues when only one sensor sees the object).

    Args:
        frames: per-frame cuboid DataFrames (PandaSet columns; the sensor/sibling columns
            are optional).
    Returns:
        the same number of DataFrames, each a subset of its input rows plus ``track_id``.
    """
    tagged = [df.assign(_frame=i, _row=np.arange(len(df))) for i, df in enumerate(frames)]
    rows = pd.concat(tagged, ignore_index=True) if tagged else pd.DataFrame()
    if rows.empty:
        return [df.assign(track_id=pd.Series(dtype=object)) for df in frames]
    uuid = rows["uuid"].astype(str)
    sensor = rows["cuboids.sensor_id"].fillna(-1).astype(int) if "cuboids.sensor_id" in rows else pd.Series(-1, index=rows.index)
    sibling = rows["cuboids.sibling_id"] if "cuboids.sibling_id" in rows else pd.Series("-", index=rows.index)

    parent: dict[str, str] = {}

    def find(a: str) -> str:
        parent.setdefault(a, a)
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for u, s in zip(uuid, sibling):
        find(u)
        if isinstance(s, str) and s not in ("", "-", u):
            ra, rb = find(u), find(s)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    root = uuid.map(find)
    is_gt = (sensor == 1).astype(int)  # 0 for Pandar64 / merged rows, 1 for PandarGT rows
    stats = (
        pd.DataFrame({"uuid": uuid, "root": root, "gt": is_gt})
        .groupby("uuid", sort=False)
        .agg(root=("root", "first"), gt=("gt", "min"), n=("gt", "size"))
        .reset_index()
        .sort_values(["gt", "n", "uuid"], ascending=[True, False, True])
    )
    canonical = stats.groupby("root", sort=False)["uuid"].first()
    track_id = root.map(canonical)
    pref = (uuid != track_id).astype(int) * 2 + is_gt
    keep = (
        pd.DataFrame({"frame": rows["_frame"], "track": track_id, "pref": pref, "uuid": uuid})
        .sort_values(["frame", "track", "pref", "uuid"])
        .drop_duplicates(["frame", "track"])
        .index
    )
    kept = rows.loc[keep].assign(track_id=track_id.loc[keep]).sort_values(["_frame", "_row"])
    out = []
    for i, df in enumerate(frames):
        sel = kept[kept["_frame"] == i]
        out.append(df.iloc[sel["_row"].to_numpy()].assign(track_id=sel["track_id"].to_numpy()))
    return out


def cuboid_poses(table: pd.DataFrame) -> np.ndarray:
    """(R,) PandaSet cuboid rows -> (R, 4, 4) box-to-PandaSet-world, x along the heading."""
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :3] = rot_z(table["yaw"].to_numpy(np.float64) + np.pi / 2)
    poses[:, :3, 3] = table[["position.x", "position.y", "position.z"]].to_numpy(np.float64)
    return poses


def _tracks_from_cuboids(frames: list[pd.DataFrame], world: np.ndarray) -> list[ActorTrack]:
    """De-duplicated per-frame cuboids -> :class:`ActorTrack` list (world = omnire world)."""
    F = len(frames)
    rows = pd.concat([df.assign(_frame=i) for i, df in enumerate(frames)], ignore_index=True)
    if rows.empty:
        return []
    box_to_world = world[None] @ cuboid_poses(rows)  # (R, 4, 4)
    # PandaSet: dimensions.x = width, .y = length, .z = height -> (length, width, height)
    lwh = rows[["dimensions.y", "dimensions.x", "dimensions.z"]].to_numpy(np.float64)  # (R, 3)
    tracks = []
    for tid, idx in rows.groupby("track_id", sort=True).indices.items():
        sub = rows.iloc[idx]
        frame_idx = sub["_frame"].to_numpy()
        present = np.zeros(F, dtype=bool)
        present[frame_idx] = True
        poses = np.full((F, 4, 4), np.nan)
        poses[frame_idx] = box_to_world[idx]
        poses = hold_absent_poses(poses, present)  # never NaN where the actor is absent
        own = sub[sub["uuid"].astype(str) == tid]
        label = str((own if len(own) else sub)["label"].mode().iloc[0])
        stationary = bool(sub["stationary"].astype(bool).all()) if "stationary" in sub else False
        tracks.append(
            ActorTrack(
                track_id=str(tid),
                class_name=label,
                category=category_of(label),
                poses=poses,
                size=lwh[idx].max(axis=0),
                present=present,
                stationary=stationary,
            )
        )
    return tracks


# ----------------------------------------------------------------------------- dataparser
class PandasetDataparser(Dataparser):
    """Reads one PandaSet sequence (see the module docstring for layout and conventions)."""

    config: "PandasetConfig"

    def parse(self) -> SceneData:
        cfg = self.config
        root = Path(cfg.data)
        if not root.is_dir():
            raise MissingFileError(
                f"PandaSet scene directory {root} does not exist; expected one PandaSet sequence "
                "directory holding camera/, lidar/ and annotations/ (e.g. data/demo/pandaset_002)"
            )
        self._check_options(root)

        # The LiDAR clock defines the frames of a PandaSet log; its poses define the world.
        lidar_dir = root / "lidar"
        lidar_times = _read_json(lidar_dir / "timestamps.json", "LiDAR timestamps (list of seconds)")
        if not isinstance(lidar_times, list) or not lidar_times:
            raise SceneDataError(f"{lidar_dir / 'timestamps.json'}: expected a non-empty list of seconds")
        n_log = len(lidar_times)
        lidar_poses = _pose_matrices(
            _read_json_list(lidar_dir / "poses.json", n_log, "LiDAR poses"), lidar_dir / "poses.json"
        )  # (N, 4, 4) Pandar64-to-PandaSet-world
        start, end = self._frame_range(root, n_log)
        frames = np.arange(start, end)
        source_frames = self._source_frames(root, n_log)[start:end]
        world = world_change(lidar_poses[start])  # (4, 4) PandaSet world -> omnire world

        cameras = [self._camera(root, name, n_log, frames, world) for name in cfg.cameras]
        lidar = None
        if cfg.load_lidar:
            track = self._pandar64_track(root, n_log, world)
            lidar = self._lidar(lidar_dir, lidar_poses, track, np.asarray(lidar_times, np.float64), frames,
                                source_frames, world)
        tracks = self._tracks(root, frames, world)
        train, test = holdout_split(len(frames), cfg.holdout_every)
        name = root.resolve().name
        scene = SceneData(
            name=name if name.startswith("pandaset") else f"pandaset_{name}",
            cameras=cameras,
            frame_timestamps=np.asarray(lidar_times, dtype=np.float64)[start:end],
            source_frames=source_frames,
            train_frames=train,
            test_frames=test,
            lidar=lidar,
            tracks=tracks,
            ego_poses=world[None] @ lidar_poses[start:end] @ _EGO_IN_LIDAR[None],
            attribution=ATTRIBUTION,
            # cuboids are drawn on the sweep's points: a moving actor's box is where the
            # sensor saw it, 0.05-0.1 s before the frame's timestamp (tools/box_timing.py)
            box_timing="sweep",
        )
        return scene.validate()

    # -- checks ---------------------------------------------------------------------------
    def _check_options(self, root: Path) -> None:
        cfg = self.config
        cfg.check()
        on_disk = [c for c in CAMERAS if (root / "camera" / c).is_dir()]
        if not cfg.cameras:
            raise SceneDataError(f"cameras: empty; cameras in {root / 'camera'}: {on_disk}")
        for name in cfg.cameras:
            if name not in CAMERAS:
                raise SceneDataError(
                    f"cameras: {name!r} is not a PandaSet camera; PandaSet cameras: {list(CAMERAS)}; "
                    f"present in {root / 'camera'}: {on_disk}"
                )
            if name not in on_disk:
                raise SceneDataError(
                    f"cameras: {name!r} is not in this sequence ({root / 'camera' / name} does not "
                    f"exist); cameras present: {on_disk}"
                )
        if len(set(cfg.cameras)) != len(cfg.cameras):
            raise SceneDataError(f"cameras: {list(cfg.cameras)} lists a camera twice")
        bad = [s for s in cfg.lidar_sensors if s not in LIDAR_SENSORS]
        if bad or not cfg.lidar_sensors:
            raise SceneDataError(
                f"lidar_sensors: {list(cfg.lidar_sensors)}; expected a non-empty subset of "
                f"{ {k: v for k, v in LIDAR_SENSORS.items()} }"
            )
        if cfg.max_lidar_points_per_frame < 0:
            raise SceneDataError(
                f"max_lidar_points_per_frame: {cfg.max_lidar_points_per_frame}, expected >= 0 (0 keeps all)"
            )

    def _frame_range(self, root: Path, n_log: int) -> tuple[int, int]:
        start, end = self.config.start_frame, self.config.end_frame
        stop = n_log if end == -1 else end
        if not (0 <= start < stop <= n_log) or end < -1:
            raise SceneDataError(
                f"frame range start_frame={start}, end_frame={end} is outside the log: {root} has "
                f"frames 0..{n_log - 1} ({n_log} frames); end_frame is exclusive, -1 = to the end"
            )
        return start, stop

    def _source_frames(self, root: Path, n_log: int) -> np.ndarray:
        path = root / "meta" / "source_frames.json"
        if not path.is_file():
            return np.arange(n_log)
        numbers = _read_json_list(path, n_log, "original frame numbers of a cut (ints)")
        if not all(isinstance(v, int) for v in numbers):
            raise SceneDataError(f"{path}: expected a list of {n_log} ints")
        return np.asarray(numbers, dtype=np.int64)

    # -- sensors ---------------------------------------------------------------------------
    def _camera(self, root: Path, name: str, n_log: int, frames: np.ndarray, world: np.ndarray) -> CameraSequence:
        cam_dir = root / "camera" / name
        k = _read_json(cam_dir / "intrinsics.json", "intrinsics {fx, fy, cx, cy} in pixels")
        try:
            fx, fy, cx, cy = (float(k[key]) for key in ("fx", "fy", "cx", "cy"))
        except (KeyError, TypeError, ValueError):
            raise SceneDataError(
                f"{cam_dir / 'intrinsics.json'}: expected an object with numbers fx, fy, cx, cy"
            ) from None
        poses = _pose_matrices(_read_json_list(cam_dir / "poses.json", n_log, f"{name} poses"), cam_dir / "poses.json")
        times = _read_json_list(cam_dir / "timestamps.json", n_log, f"{name} timestamps (seconds)")

        paths = [_frame_file(cam_dir, int(f), ".jpg") for f in frames]
        require_files(paths, f"image of camera {name}")
        # PandaSet's K maps to continuous image coordinates with pixel centres at +0.5 (its
        # devkit's projection keeps 0 < u < width, 0 < v < height), omnire's convention: no
        # shift, and resizing is a plain multiplication (the processed reader agrees).
        K0 = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return loaded_camera(name, paths, K0, image_size(paths[0]), self.config.scale, "half",
                             cam_to_world=world[None] @ poses[frames],  # (F, 4, 4) OpenCV camera-to-world
                             ego_mask_path=EGO_MASKS.get(name),
                             timestamps=np.asarray(times, dtype=np.float64)[frames])

    def _pandar64_track(self, root: Path, n_log: int, world: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """The Pandar64's calibrated poses (omnire world, x-forward axes) at the front camera's
        timestamps for the whole log (``pandar64.sensor_track``), or None for a sequence without
        the front camera's poses (then no beams)."""
        cam_dir = root / "camera" / "front_camera"
        if not (cam_dir / "poses.json").is_file():
            return None
        poses = _pose_matrices(_read_json_list(cam_dir / "poses.json", n_log, "front_camera poses"), cam_dir / "poses.json")
        stamps = _read_json_list(cam_dir / "timestamps.json", n_log, "front_camera timestamps (seconds)")
        try:
            stamps = np.asarray(stamps, dtype=np.float64)
        except (TypeError, ValueError):
            stamps = np.full(n_log, np.nan)
        if not (np.isfinite(stamps).all() and (np.diff(stamps) > 0).all()):
            raise SceneDataError(f"{cam_dir / 'timestamps.json'}: expected {n_log} increasing seconds")
        return stamps, pandar64.sensor_track(world[None] @ poses)

    def _lidar(
        self, lidar_dir: Path, lidar_poses: np.ndarray, track: Optional[tuple[np.ndarray, np.ndarray]],
        lidar_times: np.ndarray, frames: np.ndarray, source_frames: np.ndarray, world: np.ndarray
    ) -> LidarSweeps:
        """The sweeps of ``frames``; with the Pandar64's ``track`` (times (K,), poses (K, 4, 4)),
        its poses at the frames' timestamps and the beam of each of its returns, else the
        poses of ``lidar_poses`` (N, 4, 4) (lidar/poses.json) and no beams."""
        cfg = self.config
        columns = ("x", "y", "z", "i", "t", "d")
        points: list[Optional[np.ndarray]] = []
        intensity: list[Optional[np.ndarray]] = []
        times: list[Optional[np.ndarray]] = []
        beams: list[Optional[np.ndarray]] = []
        sensor_to_world = np.full((len(frames), 4, 4), np.nan)  # NaN where the frame has no LiDAR file
        for j, (f, src) in enumerate(zip(frames, source_frames)):
            path = _frame_file(lidar_dir, int(f), ".pkl.gz")
            if not path.is_file():  # real gaps in PandaSet logs (002 lacks 56-58 and 71)
                points.append(None)
                intensity.append(None)
                times.append(None)
                beams.append(None)
                continue
            table = _read_frame_table(path, columns, "LiDAR point cloud")
            keep = np.flatnonzero(np.isin(table["d"].to_numpy(), list(cfg.lidar_sensors)))
            keep = thin_points(keep, cfg.max_lidar_points_per_frame, src)  # keyed by the source frame number
            xyz = table[["x", "y", "z"]].to_numpy(np.float64)[keep]  # (N, 3) PandaSet world
            xyz = xyz @ world[:3, :3].T + world[:3, 3]
            if not np.isfinite(xyz).all():
                raise SceneDataError(f"{path}: non-finite x, y, z values")
            strength = BYTE_INTENSITY.to_unit(table["i"].to_numpy(np.float64)[keep], f"{path}: column i (intensity)")
            stamp = table["t"].to_numpy(np.float64)[keep]
            if not np.isfinite(stamp).all():
                raise SceneDataError(f"{path}: column t (per-point time) holds NaN or inf; expected seconds")
            points.append(xyz.astype(np.float32))
            intensity.append(strength)
            times.append(stamp)
            if track is None:  # no calibrated pose: the pose of lidar/poses.json, no beams
                sensor_to_world[j] = world @ lidar_poses[f] @ _EGO_IN_LIDAR
                continue
            # One pose per frame: the Pandar64's (the PandarGT sits ~1 m apart), in x-forward axes.
            sensor_to_world[j] = pandar64.sensor_poses_at(*track, lidar_times[f:f + 1])[0]
            beam = np.full(len(keep), -1, dtype=np.int16)  # -1: a PandarGT return
            mine = table["d"].to_numpy()[keep] == 0
            beam[mine] = pandar64.beams_of(xyz[mine], stamp[mine], *track)
            beams.append(beam)
        calibrated = track is not None
        return LidarSweeps(points=points, origins=sensor_to_world[:, :3, 3].copy(), intensity=intensity, times=times,
                           beams=beams if calibrated else None, sensor_to_world=sensor_to_world,
                           beam_model=pandar64.BEAM_MODEL if calibrated else None)

    def _tracks(self, root: Path, frames: np.ndarray, world: np.ndarray) -> list[ActorTrack]:
        box_dir = root / "annotations" / "cuboids"
        if not box_dir.is_dir():  # unannotated sequences (PandaSet's test split): no actors
            return []
        tables = [
            _read_frame_table(_frame_file(box_dir, int(f), ".pkl.gz"), _CUBOID_COLUMNS, "cuboid annotations")
            for f in frames
        ]
        return _tracks_from_cuboids(deduplicate_cuboids(tables), world)



@dataclasses.dataclass
class PandasetConfig(DataparserConfig):
    """PandaSet sequence in the dataset's own layout (camera/, lidar/, annotations/cuboids/)."""

    _target: Type = dataclasses.field(default_factory=lambda: PandasetDataparser)
    data: Path = Path("data/demo/pandaset_002")
    """Scene directory: one PandaSet sequence (holds camera/, lidar/, annotations/)."""
    cameras: tuple[str, ...] = CAMERAS[:3]
    """Cameras to load: any of front_camera, front_left_camera, front_right_camera, left_camera, right_camera, back_camera."""
    start_frame: int = 0
    """First frame to load (index of the files on disk, 0-based)."""
    end_frame: int = -1
    """Frame after the last one to load (exclusive); -1 loads to the end of the log."""
    load_lidar: bool = True
    """Load the LiDAR point clouds (needed for LiDAR initialisation and the depth loss)."""
    lidar_sensors: tuple[int, ...] = (0, 1)
    """LiDAR sensors to keep: 0 = Pandar64 (360 degrees), 1 = PandarGT (forward-facing)."""
    max_lidar_points_per_frame: int = 0
    """Randomly thin each sweep to at most this many points (fixed seed); 0 keeps all points."""
