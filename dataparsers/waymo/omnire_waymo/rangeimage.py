"""Waymo range images: decoding, conversion to points, and building them from points.

Conventions of the Waymo Open Dataset v1 (dataset.proto comments and the dataset's own
conversion utilities, read for facts):

- A range image is a zlib-compressed serialized ``MatrixFloat`` of shape (H, W, 4): range
  (metres; <= 0 means no return), intensity, elongation, no-label-zone flag.
- Row i has the inclination ``incl[H - 1 - i]`` of the calibration's beam inclinations
  (stored ascending, so row 0 is the highest beam). Without explicit inclinations they are
  uniform: ``incl[k] = min + (k + 0.5) / H * (max - min)``.
- Column j has the azimuth ``pi - (2 j + 1) pi / W`` in the *vehicle* frame (column 0 looks
  backwards-left, azimuth decreases to the right); in the sensor frame that is minus the yaw
  of the LiDAR extrinsic, ``atan2(E[1, 0], E[0, 0])``.
- Sensor point: ``r (cos az cos incl, sin az cos incl, sin incl)``; vehicle point =
  extrinsic (sensor -> vehicle) applied to it; global point = the pixel's vehicle pose
  (top LiDAR: ``range_image_pose_compressed``, (H, W, 6) roll, pitch, yaw, x, y, z with
  R = Rz(yaw) Ry(pitch) Rx(roll)) or else the frame's vehicle pose applied to that.
- Only the first return carries the pixel poses; the second return uses the same ones.
"""
from __future__ import annotations

import zlib
from typing import Optional

import numpy as np

from omnire_waymo.wod import dataset_pb2


class RangeImageError(ValueError):
    """A compressed matrix cannot be decoded (the caller adds file and field to the message)."""


# ----------------------------------------------------------------------------- matrices
def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if pos >= len(buf):
            raise IndexError
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7


def _fast_matrix(raw: bytes) -> Optional[np.ndarray]:
    """The common wire layout of a MatrixFloat (one packed ``data`` field, then ``shape``)
    decoded without materialising a Python float per value; None for any other layout (the
    caller then parses with the generated message class)."""
    try:
        pos, data, shape = 0, None, None
        while pos < len(raw):
            tag, pos = _varint(raw, pos)
            if tag not in (0x0A, 0x12):  # field 1 (data) / 2 (shape), length-delimited
                return None
            n, pos = _varint(raw, pos)
            if pos + n > len(raw):
                return None
            if tag == 0x0A:
                if data is not None or n % 4:
                    return None
                data = np.frombuffer(raw, dtype="<f4", count=n // 4, offset=pos)
            else:
                msg = dataset_pb2.MatrixShape()
                msg.ParseFromString(raw[pos:pos + n])
                shape = tuple(msg.dims)
            pos += n
    except Exception:  # noqa: BLE001 - any oddity (truncation, bad shape): take the generic path
        return None
    if data is None or shape is None or int(np.prod(shape)) != data.size:
        return None
    return data.reshape(shape)


def decode_matrix_float(compressed: bytes) -> np.ndarray:
    """zlib-compressed serialized ``MatrixFloat`` -> float32 array of its ``shape.dims``."""
    try:
        raw = zlib.decompress(compressed)
    except zlib.error as exc:
        raise RangeImageError(f"not zlib-compressed data ({exc})") from None
    fast = _fast_matrix(raw)
    if fast is not None:
        return fast.astype(np.float32)  # copy: owns its memory, writable
    msg = dataset_pb2.MatrixFloat()
    try:
        msg.ParseFromString(raw)
    except Exception as exc:  # google.protobuf.message.DecodeError
        raise RangeImageError(f"not a serialized MatrixFloat ({exc})") from None
    dims = tuple(msg.shape.dims)
    values = np.fromiter(msg.data, dtype=np.float32, count=len(msg.data))
    if not dims or int(np.prod(dims)) != values.size:
        raise RangeImageError(f"MatrixFloat holds {values.size} values but its shape is {list(dims)}")
    return values.reshape(dims)


def encode_matrix_float(array: np.ndarray, level: int = 6) -> bytes:
    """float32 array -> zlib-compressed serialized ``MatrixFloat`` (row-major, shape kept)."""
    array = np.ascontiguousarray(array, dtype=np.float32)
    msg = dataset_pb2.MatrixFloat()
    msg.shape.dims.extend(array.shape)
    # Serialise the packed field by hand around the generated message's shape: a Python
    # float per value through ``extend`` costs ~0.1 s per megapixel image.
    shape = msg.SerializeToString()
    body = array.astype("<f4").tobytes()
    return zlib.compress(b"\x0a" + _encode_varint(len(body)) + body + shape, level)


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        b = value & 0x7F
        value >>= 7
        if value:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


# ----------------------------------------------------------------------------- geometry
def uniform_inclinations(inclination_min: float, inclination_max: float, height: int) -> np.ndarray:
    """(H,) ascending beam inclinations (radians) of a LiDAR given only min/max."""
    k = np.arange(height, dtype=np.float64)
    return inclination_min + (k + 0.5) / height * (inclination_max - inclination_min)


def row_inclinations(calibration, height: int) -> np.ndarray:
    """(H,) inclination of each range image row (row 0 = highest) for a LaserCalibration."""
    if len(calibration.beam_inclinations):
        incl = np.asarray(calibration.beam_inclinations, dtype=np.float64)
        if incl.size != height:
            raise RangeImageError(
                f"{incl.size} beam_inclinations for a range image of {height} rows"
            )
    else:
        incl = uniform_inclinations(calibration.beam_inclination_min, calibration.beam_inclination_max, height)
    return incl[::-1].copy()


def column_azimuths(width: int) -> np.ndarray:
    """(W,) vehicle-frame azimuth (radians) of each range image column."""
    j = np.arange(width, dtype=np.float64)
    return np.pi - (2.0 * j + 1.0) * np.pi / width


def euler_to_rotmat(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(...,) roll, pitch, yaw (3-2-1 Euler) -> (..., 3, 3) R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def rotate_euler(p: np.ndarray, roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(N, 3) vectors rotated by Rz(yaw) Ry(pitch) Rx(roll), per row, without forming the
    (N, 3, 3) matrices (a third of the memory traffic of an einsum over them)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    c, s = np.cos(roll), np.sin(roll)
    y, z = c * y - s * z, s * y + c * z
    c, s = np.cos(pitch), np.sin(pitch)
    x, z = c * x + s * z, -s * x + c * z
    c, s = np.cos(yaw), np.sin(yaw)
    x, y = c * x - s * y, s * x + c * y
    return np.stack([x, y, z], 1)


def rotmat_to_euler(R: np.ndarray) -> tuple[float, float, float]:
    """(3, 3) rotation -> (roll, pitch, yaw) with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(R[2, 1], R[2, 2]))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def range_image_to_points(
    ranges: np.ndarray,
    inclinations: np.ndarray,
    extrinsic: np.ndarray,
    vehicle_pose: np.ndarray,
    pixel_pose: Optional[np.ndarray] = None,
    world_from_global: Optional[np.ndarray] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels of a range image -> points, in float64.

    Args:
        ranges: (H, W) range channel (metres; pixels with range <= 0 have no return).
        inclinations: (H,) inclination per row (row 0 = highest), see :func:`row_inclinations`.
        extrinsic: (4, 4) LiDAR-to-vehicle transform.
        vehicle_pose: (4, 4) vehicle-to-global pose of the frame (used where ``pixel_pose``
            is None).
        pixel_pose: optional (H, W, 6) per-pixel vehicle pose (roll, pitch, yaw, x, y, z),
            vehicle-to-global.
        world_from_global: optional (4, 4) applied last (e.g. global -> omnire world).
    Returns:
        points (N, 3) float64 and the (N, 2) int (row, column) of each, row-major order.
    """
    H, W = ranges.shape
    if inclinations.shape != (H,):
        raise RangeImageError(f"{inclinations.shape[0]} inclinations for {H} rows")
    rows, cols = np.nonzero(ranges > 0)
    r = ranges[rows, cols].astype(np.float64)
    # Trigonometry per column and per row, gathered per point (cheaper than per point).
    az = column_azimuths(W) - np.arctan2(extrinsic[1, 0], extrinsic[0, 0])
    inc = np.asarray(inclinations, dtype=np.float64)
    rc = r * np.cos(inc)[rows]
    p = np.stack([rc * np.cos(az)[cols], rc * np.sin(az)[cols], r * np.sin(inc)[rows]], 1)  # (N, 3) sensor
    p = p @ extrinsic[:3, :3].T + extrinsic[:3, 3]  # vehicle frame
    post = np.eye(4) if world_from_global is None else np.asarray(world_from_global, dtype=np.float64)
    if pixel_pose is None:
        M = post @ vehicle_pose
        p = p @ M[:3, :3].T + M[:3, 3]
    else:
        if pixel_pose.shape != (H, W, 6):
            raise RangeImageError(f"pixel pose of shape {pixel_pose.shape}, expected {(H, W, 6)}")
        pp = pixel_pose[rows, cols].astype(np.float64)  # (N, 6)
        p = rotate_euler(p, pp[:, 0], pp[:, 1], pp[:, 2]) + pp[:, 3:]
        p = p @ post[:3, :3].T + post[:3, 3]
    return p, np.stack([rows, cols], 1)


# ----------------------------------------------------------------------------- writing
def cluster_inclinations(inclinations: np.ndarray, gap: float = np.deg2rad(0.05)) -> np.ndarray:
    """(N,) per-point inclinations of a spinning LiDAR -> (H,) ascending beam inclinations:
    sorted values split where consecutive ones differ by more than ``gap``, one median each."""
    v = np.sort(np.asarray(inclinations, dtype=np.float64))
    if v.size == 0:
        return v
    cuts = np.flatnonzero(np.diff(v) > gap) + 1
    return np.array([np.median(c) for c in np.split(v, cuts)])


def points_to_range_images(
    points_sensor: np.ndarray, beam_inclinations: np.ndarray, width: int, extrinsic_yaw: float = 0.0
) -> tuple[np.ndarray, np.ndarray, int]:
    """Bin points of one sweep into a first- and a second-return range image.

    Each point goes to the row of the nearest beam inclination and the column whose centre
    azimuth (vehicle frame) it is nearest to; a point exactly between two column centres
    goes to the smaller column index (stable under rounding noise, so samples one column
    width apart never share a column). Per pixel the nearest point is the
    first return, the next one the second; further points are dropped.

    Args:
        points_sensor: (N, 3) points in the LiDAR frame.
        beam_inclinations: (H,) ascending beam inclinations (radians).
        width: W, number of columns.
        extrinsic_yaw: yaw of the LiDAR extrinsic, atan2(E[1, 0], E[0, 0]).
    Returns:
        ranges of the first and second return, (H, W) float32 each (0 = no return), and the
        number of points dropped (a third or later point in a pixel).
    """
    p = np.asarray(points_sensor, dtype=np.float64)
    H = len(beam_inclinations)
    r = np.linalg.norm(p, axis=1)
    ok = r > 0
    p, r = p[ok], r[ok]
    inc = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    beams = np.asarray(beam_inclinations, dtype=np.float64)
    k = np.clip(np.searchsorted(beams, inc), 1, H - 1) if H > 1 else np.zeros(len(inc), np.int64)
    if H > 1:
        k = np.where(np.abs(inc - beams[k - 1]) <= np.abs(inc - beams[k]), k - 1, k)
    row = H - 1 - k
    az = np.arctan2(p[:, 1], p[:, 0]) + extrinsic_yaw  # vehicle-frame azimuth
    c = width - 0.5 - (az + np.pi) / (2 * np.pi) * width  # continuous column, centres at integers
    col = np.floor(c + 0.5 - 1e-9).astype(np.int64) % width
    order = np.lexsort((r, col, row))  # by pixel, nearest first
    pix = (row * width + col)[order]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    rank = np.arange(len(pix)) - np.maximum.accumulate(np.where(first, np.arange(len(pix)), 0))
    out = [np.zeros(H * width, np.float32), np.zeros(H * width, np.float32)]
    for ret in (0, 1):
        sel = rank == ret
        out[ret][pix[sel]] = r[order][sel]
    return out[0].reshape(H, width), out[1].reshape(H, width), int((rank > 1).sum())
