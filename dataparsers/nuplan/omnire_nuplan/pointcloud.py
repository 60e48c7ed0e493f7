"""nuPlan's merged LiDAR blobs (``sensor_blobs/<log>/MergedPointCloud/<token>.pcd``).

Format (nuplan-devkit ``nuplan/database/utils/pointclouds/pointcloud.py``, ``PointCloud.parse``;
``lidar_pc.py`` ``LidarPc.load`` picks the parser by file suffix):

- ``.pcd``: PCL's point-cloud format. Text header lines (``#`` comments, then ``VERSION``,
  ``FIELDS``, ``SIZE``, ``TYPE``, ``COUNT``, ``WIDTH``, ``HEIGHT``, ``VIEWPOINT``, ``POINTS``,
  ``DATA``), then ``POINTS`` binary records of the listed fields (TYPE ``F``/``I``/``U`` of
  SIZE bytes, COUNT 1 each). The devkit reads only ``DATA binary`` and ignores bytes after the
  last point. Merged clouds carry ``x y z intensity ring lidar_info`` (``to_pcd_bin2``).
- ``.bin2``: float32 rows of x, y, z, intensity, ring, lidar id (``load_pcd_bin`` version 2).

Points are in the frame of the ``lidar`` row of their ``lidar_pc`` (the devkit moves them to
the ego with ``lidar.trans_matrix``: ``nuplan_db_orm/rendering_utils.py``
``map_pointcloud_to_image``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from omnire_nuplan.database import NuPlanDataError

HEADER_KEYS = ("version", "fields", "size", "type", "count", "width", "height", "viewpoint", "points", "data")
BIN2_FIELDS = ("x", "y", "z", "intensity", "ring", "lidar_info")
MAX_HEADER_LINES = 64


def read_points(path: Path) -> np.ndarray:
    """The records of a merged point cloud blob: a structured array (N,) with at least float
    fields x, y, z (plus whatever else the blob holds: intensity, ring, lidar_info)."""
    data = path.read_bytes()
    if path.suffix == ".bin2":
        if len(data) % (4 * len(BIN2_FIELDS)):
            raise NuPlanDataError(f"{path}: {len(data)} bytes is not a whole number of {4 * len(BIN2_FIELDS)}-byte "
                                  f"points ({len(BIN2_FIELDS)} float32: {' '.join(BIN2_FIELDS)})")
        return np.frombuffer(data, dtype=np.dtype([(f, "<f4") for f in BIN2_FIELDS]))
    if path.suffix != ".pcd":
        raise NuPlanDataError(f"{path}: unknown point cloud blob suffix {path.suffix!r}; nuPlan merged clouds are "
                              ".pcd (or .bin2)")
    return parse_pcd(data, path)


def parse_pcd(data: bytes, path: Path) -> np.ndarray:
    """Records of a binary ``.pcd`` file's bytes (see the module docstring)."""
    header: dict[str, list[str]] = {}
    pos = 0
    for _ in range(MAX_HEADER_LINES):
        end = data.find(b"\n", pos)
        if end < 0:
            raise NuPlanDataError(f"{path}: .pcd header ends before its DATA line")
        try:
            line = data[pos:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise NuPlanDataError(f"{path}: .pcd header line at byte {pos} is not text; not a .pcd file") from None
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.lower()] = vals
        if key.lower() == "data":
            break
    else:
        raise NuPlanDataError(f"{path}: no DATA line in the first {MAX_HEADER_LINES} header lines; not a .pcd file")
    missing = [k for k in ("fields", "size", "type", "points", "data") if k not in header]
    if missing:
        raise NuPlanDataError(f"{path}: .pcd header lacks {', '.join(k.upper() for k in missing)}")
    fields, sizes, types = header["fields"], header["size"], header["type"]
    counts = header.get("count", ["1"] * len(fields))
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise NuPlanDataError(f"{path}: .pcd header FIELDS/SIZE/TYPE/COUNT have different lengths "
                              f"({len(fields)}/{len(sizes)}/{len(types)}/{len(counts)})")
    if header["data"] != ["binary"]:
        raise NuPlanDataError(f"{path}: .pcd DATA {' '.join(header['data'])}; nuPlan blobs are DATA binary")
    kinds = {"F": {4: "<f4", 8: "<f8"}, "I": {1: "i1", 2: "<i2", 4: "<i4", 8: "<i8"},
             "U": {1: "u1", 2: "<u2", 4: "<u4", 8: "<u8"}}
    dtype = []
    for f, s, t, c in zip(fields, sizes, types, counts):
        code = kinds.get(t, {}).get(int(s)) if s.isdigit() else None
        if code is None or c != "1":
            raise NuPlanDataError(f"{path}: .pcd field {f!r} has TYPE {t} SIZE {s} COUNT {c}; expected COUNT 1 and "
                                  "TYPE F (4/8 bytes), I or U (1/2/4/8 bytes)")
        dtype.append((f, code))
    if len({f for f, _ in dtype}) != len(dtype) or not {"x", "y", "z"} <= set(fields):
        raise NuPlanDataError(f"{path}: .pcd FIELDS {' '.join(fields)}; expected distinct names including x y z")
    try:
        n = int(header["points"][0])
    except (ValueError, IndexError):
        n = -1
    row = np.dtype(dtype)
    if n < 0 or pos + n * row.itemsize > len(data):
        raise NuPlanDataError(f"{path}: .pcd POINTS {' '.join(header['points'])} needs "
                              f"{max(n, 0) * row.itemsize} bytes of {row.itemsize}-byte records; "
                              f"the file has {len(data) - pos} after the header (truncated?)")
    return np.frombuffer(data, dtype=row, count=n, offset=pos)  # bytes after the last point are ignored


def write_pcd(points: np.ndarray) -> bytes:
    """A binary ``.pcd`` holding the records of the structured array ``points`` (N,)."""
    codes = {"f": "F", "i": "I", "u": "U"}
    names = points.dtype.names
    head = "\n".join([
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(names),
        "SIZE " + " ".join(str(points.dtype[n].itemsize) for n in names),
        "TYPE " + " ".join(codes[points.dtype[n].kind] for n in names),
        "COUNT " + " ".join("1" for _ in names),
        f"WIDTH {len(points)}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {len(points)}",
        "DATA binary",
    ]) + "\n"
    little = points.astype(points.dtype.newbyteorder("<"))
    return head.encode("ascii") + little.tobytes()
