"""Reading the parts of one Argoverse 2 sensor log, each on its own (no SceneData).

Files (AV2 sensor dataset, ``<split>/<log_id>/``), all Apache Feather read with pyarrow::

    city_SE3_egovehicle.feather          timestamp_ns, qw qx qy qz, tx_m ty_m tz_m (ego -> city)
    calibration/egovehicle_SE3_sensor.feather   sensor_name, qw qx qy qz, tx_m ty_m tz_m (sensor -> ego)
    calibration/intrinsics.feather       sensor_name, fx_px fy_px cx_px cy_px, k1 k2 k3, height_px width_px
    annotations.feather                  timestamp_ns, track_uuid, category, length_m width_m height_m,
                                         qw qx qy qz, tx_m ty_m tz_m (box -> ego at timestamp_ns),
                                         num_interior_pts
    sensors/lidar/<timestamp_ns>.feather x y z (ego frame at timestamp_ns), intensity, laser_number, offset_ns
    sensors/cameras/<camera>/<timestamp_ns>.jpg

Quaternions are wxyz (scalar first). Conventions checked on the real logs in
``../shared/data/av2`` (tests/test_argoverse2_real.py): camera sensor frames are OpenCV axes
(x right, y down, z forward: ring_front_center's z axis is ego +x, its y axis ego -z);
boxes have x along the length, and the LiDAR points inside each box equal its
``num_interior_pts`` exactly; sweeps are in the ego frame at the sweep time (av2-api:
"egomotion-compensated to the egovehicle reference timestamp"); the ego origin is about
0.2-0.5 m above the road (AV2: the rear-axle centre).

Every reader here raises :class:`Av2LogError` naming the file and field it could not use.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from omnire.api import SceneDataError, interpolate_poses, quat_to_rotmat

RING_CAMERAS = (
    "ring_front_center",
    "ring_front_left",
    "ring_front_right",
    "ring_side_left",
    "ring_side_right",
    "ring_rear_left",
    "ring_rear_right",
)
"""The seven AV2 ring cameras (20 Hz), front first."""
STEREO_CAMERAS = ("stereo_front_left", "stereo_front_right")
"""The two forward stereo cameras (20 Hz)."""
LIDAR_SENSOR = "up_lidar"
"""Sensor whose position is taken as the origin of every sweep (the two stacked Velodynes
sit 0.1 m apart; a sweep holds both)."""

POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
INTRINSICS_COLUMNS = ("sensor_name", "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "height_px", "width_px")
ANNOTATION_COLUMNS = ("timestamp_ns", "track_uuid", "category", "length_m", "width_m", "height_m",
                      *POSE_COLUMNS, "num_interior_pts")
SWEEP_COLUMNS = ("x", "y", "z", "intensity", "laser_number", "offset_ns")

# AV2 sensor-dataset categories (av2-api AnnotationCategories) -> omnire categories. Vehicles
# follow av2-api's own VehicleCategories grouping (towed trailers included: rigid boxes).
# Riders are cyclists; a ridden bicycle/motorcycle has its own separate box, so the
# vehicles themselves (and other wheeled devices) are "other", like street furniture.
CATEGORY_MAP: dict[str, str] = {
    "REGULAR_VEHICLE": "vehicle",
    "LARGE_VEHICLE": "vehicle",
    "BUS": "vehicle",
    "ARTICULATED_BUS": "vehicle",
    "SCHOOL_BUS": "vehicle",
    "BOX_TRUCK": "vehicle",
    "TRUCK": "vehicle",
    "TRUCK_CAB": "vehicle",
    "VEHICULAR_TRAILER": "vehicle",
    "RAILED_VEHICLE": "vehicle",
    "MESSAGE_BOARD_TRAILER": "vehicle",
    "TRAFFIC_LIGHT_TRAILER": "vehicle",
    "PEDESTRIAN": "human",
    "OFFICIAL_SIGNALER": "human",
    "BICYCLIST": "cyclist",
    "MOTORCYCLIST": "cyclist",
    "WHEELED_RIDER": "cyclist",
    "BICYCLE": "other",
    "MOTORCYCLE": "other",
    "WHEELED_DEVICE": "other",
    "WHEELCHAIR": "other",
    "STROLLER": "other",
    "ANIMAL": "other",
    "DOG": "other",
    "BOLLARD": "other",
    "CONSTRUCTION_BARREL": "other",
    "CONSTRUCTION_CONE": "other",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN": "other",
    "SIGN": "other",
    "STOP_SIGN": "other",
}


class Av2LogError(SceneDataError):
    """A file of an AV2 log is missing or malformed (the message names file and field)."""


def category_of(label: str) -> str:
    """AV2 annotation category -> omnire actor category; unknown labels are "other"."""
    return CATEGORY_MAP.get(label, "other")


# ----------------------------------------------------------------------------- feather tables
def read_columns(path: Path, columns: Sequence[str], what: str) -> dict[str, np.ndarray]:
    """The named columns of a Feather file as numpy arrays (strings as object arrays).

    Only the named columns are read (memory-mapped), so wide or large files cost what is used.
    """
    import pyarrow as pa
    import pyarrow.feather as feather
    import pyarrow.ipc

    if not path.is_file():
        raise Av2LogError(f"{path}: missing {what}")
    try:
        with pa.memory_map(str(path)) as source:
            names = pa.ipc.open_file(source).schema.names
        missing = [c for c in columns if c not in names]
        if missing:
            raise Av2LogError(f"{path}: {what} lacks columns {missing}; expected columns {list(columns)} "
                              f"(found {names})")
        table = feather.read_table(path, columns=list(columns), memory_map=True)
    except (pa.ArrowException, OSError) as exc:
        raise Av2LogError(f"{path}: not a readable Feather (Arrow IPC) file ({exc}); expected {what}") from None
    out = {}
    for c in columns:
        col = table.column(c)
        if col.null_count:
            raise Av2LogError(f"{path}: column {c!r} of the {what} has {col.null_count} missing values")
        out[c] = col.to_numpy(zero_copy_only=False)
    return out


def _numeric(cols: dict[str, np.ndarray], names: Sequence[str], path: Path) -> np.ndarray:
    """(N, len(names)) float64 of numeric columns; non-numeric or non-finite -> error."""
    arrays = []
    for n in names:
        a = cols[n]
        if not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
            raise Av2LogError(f"{path}: column {n!r} has type {a.dtype}, expected numbers")
        arrays.append(a.astype(np.float64))
    out = np.stack(arrays, axis=1) if arrays else np.zeros((0, 0))
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any():
        raise Av2LogError(f"{path}: row {int(np.flatnonzero(bad)[0])} has NaN or inf in {list(names)}")
    return out


def se3_from_columns(cols: dict[str, np.ndarray], path: Path) -> np.ndarray:
    """Rows with qw qx qy qz tx_m ty_m tz_m -> (N, 4, 4) rigid transforms."""
    v = _numeric(cols, POSE_COLUMNS, path)  # (N, 7)
    norm = np.linalg.norm(v[:, :4], axis=1)
    bad = np.abs(norm - 1.0) > 1e-3
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise Av2LogError(f"{path}: row {i}: quaternion (qw, qx, qy, qz) has norm {norm[i]:.6g}, expected 1")
    T = np.tile(np.eye(4), (len(v), 1, 1))
    if len(v):
        T[:, :3, :3] = quat_to_rotmat(v[:, :4])
        T[:, :3, 3] = v[:, 4:]
    return T


def _timestamps(a: np.ndarray, path: Path, field: str = "timestamp_ns") -> np.ndarray:
    if not np.issubdtype(a.dtype, np.integer):
        raise Av2LogError(f"{path}: column {field!r} has type {a.dtype}, expected integer nanoseconds")
    return a.astype(np.int64)


# ----------------------------------------------------------------------------- ego poses
@dataclasses.dataclass
class EgoPoses:
    """Ego-to-city poses of a log at their own timestamps.

    Attributes:
        timestamps_ns: (P,) strictly increasing int64 nanoseconds.
        city_SE3_ego: (P, 4, 4) ego -> city.
        path: the file they came from (for messages).
    """

    timestamps_ns: np.ndarray
    city_SE3_ego: np.ndarray
    path: Path

    max_extrapolation_ns = 50_000_000
    """Queries up to 50 ms outside the recorded poses hold the nearest pose; further is an error."""

    def at(self, timestamps_ns: np.ndarray) -> np.ndarray:
        """(Q,) int64 ns -> (Q, 4, 4) ego -> city, SLERP/linear between the two recorded poses
        around each time (recorded times are returned exactly)."""
        q = np.atleast_1d(np.asarray(timestamps_ns, dtype=np.int64))
        t0, t1 = int(self.timestamps_ns[0]), int(self.timestamps_ns[-1])
        far = (q < t0 - self.max_extrapolation_ns) | (q > t1 + self.max_extrapolation_ns)
        if far.any():
            raise Av2LogError(
                f"{self.path}: no ego pose near timestamp_ns {int(q[far][0])}: poses cover {t0}..{t1} "
                f"(a sensor time more than {self.max_extrapolation_ns / 1e6:.0f} ms outside them)"
            )
        # Seconds relative to the first pose: float64 keeps nanoseconds exactly over hours.
        known = (self.timestamps_ns - t0).astype(np.float64) * 1e-9
        return interpolate_poses(known, self.city_SE3_ego, (q - t0).astype(np.float64) * 1e-9)


def read_ego_poses(log_dir: Path) -> EgoPoses:
    """``city_SE3_egovehicle.feather`` -> :class:`EgoPoses` (rows sorted by time; exact
    duplicates of a timestamp are dropped, conflicting ones are an error)."""
    path = log_dir / "city_SE3_egovehicle.feather"
    cols = read_columns(path, ("timestamp_ns", *POSE_COLUMNS), "ego poses (city_SE3_egovehicle)")
    ts = _timestamps(cols["timestamp_ns"], path)
    if len(ts) == 0:
        raise Av2LogError(f"{path}: no rows; expected ego poses over the log")
    T = se3_from_columns(cols, path)
    order = np.argsort(ts, kind="stable")
    ts, T = ts[order], T[order]
    dup = np.flatnonzero(np.diff(ts) == 0)
    if len(dup):
        if not np.allclose(T[dup], T[dup + 1], atol=1e-9):
            raise Av2LogError(f"{path}: two different poses at timestamp_ns {int(ts[dup[0]])}")
        keep = np.ones(len(ts), bool)
        keep[dup + 1] = False
        ts, T = ts[keep], T[keep]
    return EgoPoses(ts, T, path)


# ----------------------------------------------------------------------------- calibration
@dataclasses.dataclass(frozen=True)
class CameraIntrinsics:
    """One row of ``calibration/intrinsics.feather``: pinhole K in AV2's pixel convention
    (pixel centres at integer coordinates), radial distortion k1 k2 k3, image size."""

    name: str
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    k2: float
    k3: float
    width: int
    height: int

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) K of the file, pixel centres at integers: AV2 states them there (av2-api
        accepts projections in [0, W-1]), so readers move the principal point by +0.5 px
        (``omnire.api.loaded_intrinsics(..., "integer")``)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        """(5,) OpenCV k1 k2 p1 p2 k3: AV2 gives the radial terms only (no tangential)."""
        return np.array([self.k1, self.k2, 0.0, 0.0, self.k3])


def read_intrinsics(log_dir: Path) -> dict[str, CameraIntrinsics]:
    """``calibration/intrinsics.feather`` -> camera name -> :class:`CameraIntrinsics`."""
    path = log_dir / "calibration" / "intrinsics.feather"
    cols = read_columns(path, INTRINSICS_COLUMNS, "camera intrinsics")
    v = _numeric(cols, INTRINSICS_COLUMNS[1:], path)  # (C, 9)
    out = {}
    for name, row in zip(cols["sensor_name"], v):
        fx, fy, cx, cy, k1, k2, k3, h, w = row
        if not (fx > 0 and fy > 0 and w >= 1 and h >= 1) or w != int(w) or h != int(h):
            raise Av2LogError(f"{path}: sensor {name!r}: fx_px {fx}, fy_px {fy}, width_px {w}, height_px {h}; "
                              "expected positive focal lengths and a positive integer image size")
        out[str(name)] = CameraIntrinsics(str(name), fx, fy, cx, cy, k1, k2, k3, int(w), int(h))
    return out


def read_sensor_poses(log_dir: Path) -> dict[str, np.ndarray]:
    """``calibration/egovehicle_SE3_sensor.feather`` -> sensor name -> (4, 4) sensor -> ego."""
    path = log_dir / "calibration" / "egovehicle_SE3_sensor.feather"
    cols = read_columns(path, ("sensor_name", *POSE_COLUMNS), "sensor extrinsics (egovehicle_SE3_sensor)")
    T = se3_from_columns(cols, path)
    return {str(n): T[i] for i, n in enumerate(cols["sensor_name"])}


def sensor_row(table: dict, name: str, path: Path, what: str):
    """``table[name]`` or an error naming the file, the sensor and the sensors present."""
    if name not in table:
        raise Av2LogError(f"{path}: no row with sensor_name {name!r} ({what}); sensors: {sorted(table)}")
    return table[name]


# ----------------------------------------------------------------------------- annotations
@dataclasses.dataclass
class Annotations:
    """Rows of ``annotations.feather`` (N cuboids).

    Attributes:
        timestamps_ns: (N,) int64 sweep time of each cuboid.
        track_uuid: (N,) str.
        category: (N,) str (AV2 category names).
        size: (N, 3) length, width, height in metres.
        ego_SE3_box: (N, 4, 4) box -> ego at the cuboid's timestamp (x along the length).
        num_interior_pts: (N,) int64 LiDAR points of that sweep inside the box.
    """

    timestamps_ns: np.ndarray
    track_uuid: np.ndarray
    category: np.ndarray
    size: np.ndarray
    ego_SE3_box: np.ndarray
    num_interior_pts: np.ndarray

    def at(self, timestamp_ns: int) -> np.ndarray:
        """Row indices of the cuboids annotated at one sweep time."""
        return np.flatnonzero(self.timestamps_ns == int(timestamp_ns))


def read_annotations(log_dir: Path) -> Optional[Annotations]:
    """``annotations.feather`` -> :class:`Annotations`, or None when the log has none (the
    AV2 test split)."""
    path = log_dir / "annotations.feather"
    if not path.exists():
        return None
    cols = read_columns(path, ANNOTATION_COLUMNS, "cuboid annotations")
    size = _numeric(cols, ("length_m", "width_m", "height_m"), path)
    if len(size) and not (size > 0).all():
        i = int(np.flatnonzero(~(size > 0).all(1))[0])
        raise Av2LogError(f"{path}: row {i}: length_m/width_m/height_m {size[i].tolist()}, expected positive")
    return Annotations(
        timestamps_ns=_timestamps(cols["timestamp_ns"], path),
        track_uuid=cols["track_uuid"].astype(str),
        category=cols["category"].astype(str),
        size=size,
        ego_SE3_box=se3_from_columns(cols, path),
        num_interior_pts=_timestamps(cols["num_interior_pts"], path, "num_interior_pts"),
    )


# ----------------------------------------------------------------------------- sensors
def timestamped_files(folder: Path, suffix: str, what: str) -> tuple[np.ndarray, list[Path]]:
    """Files ``<timestamp_ns><suffix>`` in ``folder`` -> (sorted int64 ns (K,), paths)."""
    if not folder.is_dir():
        raise Av2LogError(f"{folder}: missing folder of {what}")
    stamps, paths = [], []
    for p in folder.iterdir():
        if p.name.endswith(suffix) and not p.name.startswith("."):
            stem = p.name[: -len(suffix)]
            if not stem.isdigit():
                raise Av2LogError(f"{p}: file name must be <timestamp_ns>{suffix} ({what})")
            stamps.append(int(stem))
            paths.append(p)
    if not paths:
        raise Av2LogError(f"{folder}: no <timestamp_ns>{suffix} files ({what})")
    order = np.argsort(stamps)
    return np.asarray(stamps, dtype=np.int64)[order], [paths[i] for i in order]


def sweep_files(log_dir: Path) -> tuple[np.ndarray, list[Path]]:
    """The LiDAR sweeps of a log: (sorted int64 ns (S,), paths); they are the frame clock."""
    return timestamped_files(log_dir / "sensors" / "lidar", ".feather", "LiDAR sweeps (sensors/lidar)")


@dataclasses.dataclass
class Sweep:
    """One LiDAR sweep in the ego frame at ``timestamp_ns`` (N points).

    Attributes:
        xyz: (N, 3) float64 ego-frame metres.
        intensity: (N,) uint8; laser_number: (N,) uint8 (0-63, both stacked LiDARs);
        offset_ns: (N,) int32 capture offset from the sweep time (points are already
            motion-compensated to the sweep time).
    """

    timestamp_ns: int
    xyz: np.ndarray
    intensity: np.ndarray
    laser_number: np.ndarray
    offset_ns: np.ndarray


def read_sweep(path: Path, xyz_only: bool = False) -> Sweep:
    """``sensors/lidar/<timestamp_ns>.feather`` -> :class:`Sweep` (only x y z if ``xyz_only``)."""
    cols = read_columns(path, SWEEP_COLUMNS[:3] if xyz_only else SWEEP_COLUMNS, "LiDAR sweep")
    xyz = _numeric(cols, ("x", "y", "z"), path)
    n = len(xyz)
    empty = np.zeros(n, np.uint8)
    return Sweep(int(path.name.split(".")[0]), xyz, cols.get("intensity", empty),
                 cols.get("laser_number", empty), cols.get("offset_ns", np.zeros(n, np.int32)))


def nearest(query_ns: np.ndarray, available_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query (Q,) the index (Q,) of the nearest of the sorted ``available_ns`` (K,)
    and the signed offset available - query (Q,) in ns (ties go to the earlier one)."""
    q = np.atleast_1d(np.asarray(query_ns, dtype=np.int64))
    after = np.searchsorted(available_ns, q).clip(0, len(available_ns) - 1)
    before = (after - 1).clip(0)
    pick = np.where(np.abs(available_ns[after] - q) < np.abs(available_ns[before] - q), after, before)
    return pick, available_ns[pick] - q


def points_in_boxes(points: np.ndarray, box_poses: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """How many of ``points`` (N, 3) lie inside each box (B,): poses (B, 4, 4) box -> same
    frame as the points, sizes (B, 3) length width height; boundaries count as inside
    (as av2-api's interior test). Returns (B,) int64.

    Points are sorted by x once; each box tests only the slab of points within its
    circumradius in x."""
    points = np.asarray(points, dtype=np.float64)
    order = np.argsort(points[:, 0], kind="stable")
    xs, sorted_pts = points[order, 0], points[order]
    counts = np.zeros(len(box_poses), np.int64)
    for b, (P, size) in enumerate(zip(box_poses, sizes)):
        r = 0.5 * float(np.linalg.norm(size)) + 1e-6
        lo = np.searchsorted(xs, P[0, 3] - r, side="left")
        hi = np.searchsorted(xs, P[0, 3] + r, side="right")
        local = (sorted_pts[lo:hi] - P[:3, 3]) @ P[:3, :3]  # (n, 3) box frame
        counts[b] = int((np.abs(local) <= size / 2).all(1).sum())
    return counts
