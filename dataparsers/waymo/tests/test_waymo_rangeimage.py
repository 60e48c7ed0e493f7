"""Range images: conversion to points against a brute-force float64 reference, matrix
decoding, and building range images from points."""
from __future__ import annotations

import math
import zlib

import numpy as np
import pytest

from omnire_waymo import rangeimage
from omnire_waymo.rangeimage import RangeImageError
from omnire_waymo.wod import dataset_pb2


# ----------------------------------------------------------------------------- reference
def _mat_rx(a):
    return [[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]]


def _mat_ry(a):
    return [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]


def _mat_rz(a):
    return [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]


def _matmul(A, B):
    return [[sum(A[i][k] * B[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def _apply(M, t, p):
    return [sum(M[i][k] * p[k] for k in range(3)) + t[i] for i in range(3)]


def brute_force_points(ranges, inclinations_ascending, extrinsic, vehicle_pose, pixel_pose, post):
    """Pixel by pixel, in Python floats (float64), straight from the dataset's definitions:
    row i has inclination incl[H-1-i]; column j has azimuth (2 (W-j-0.5)/W - 1) pi minus the
    extrinsic's yaw in the sensor frame; pixel pose R = Rz(yaw) Ry(pitch) Rx(roll)."""
    H, W = ranges.shape
    E = [[float(extrinsic[i][k]) for k in range(3)] for i in range(3)]
    tE = [float(extrinsic[i][3]) for i in range(3)]
    yaw_e = math.atan2(extrinsic[1][0], extrinsic[0][0])
    out = []
    for i in range(H):
        incl = float(inclinations_ascending[H - 1 - i])
        for j in range(W):
            r = float(ranges[i, j])
            if r <= 0:
                continue
            ratio = (W - j - 0.5) / W
            az = (ratio * 2 - 1) * math.pi - yaw_e
            p = [r * math.cos(az) * math.cos(incl), r * math.sin(az) * math.cos(incl), r * math.sin(incl)]
            p = _apply(E, tE, p)
            if pixel_pose is None:
                M = [[float(vehicle_pose[a][b]) for b in range(3)] for a in range(3)]
                p = _apply(M, [float(vehicle_pose[a][3]) for a in range(3)], p)
            else:
                roll, pitch, yaw, x, y, z = (float(v) for v in pixel_pose[i, j])
                R = _matmul(_mat_rz(yaw), _matmul(_mat_ry(pitch), _mat_rx(roll)))
                p = _apply(R, [x, y, z], p)
            P = [[float(post[a][b]) for b in range(3)] for a in range(3)]
            out.append(_apply(P, [float(post[a][3]) for a in range(3)], p))
    return np.array(out)


def _random_transform(rng, angles=0.3, shift=2.0):
    roll, pitch, yaw = rng.uniform(-angles, angles, 3)
    M = np.eye(4)
    M[:3, :3] = rangeimage.euler_to_rotmat(np.array(roll), np.array(pitch), np.array(yaw))
    M[:3, 3] = rng.uniform(-shift, shift, 3)
    return M


@pytest.mark.parametrize("explicit", [True, False])
@pytest.mark.parametrize("with_pixel_pose", [True, False])
def test_range_image_to_points_matches_brute_force(explicit, with_pixel_pose):
    rng = np.random.default_rng(3 + 2 * explicit + with_pixel_pose)
    H, W = 7, 48
    ranges = rng.uniform(0.5, 80.0, (H, W)).astype(np.float32)
    ranges[rng.random((H, W)) < 0.3] = -1.0  # no return
    ranges[0, 0] = 0.0  # zero range is no return too
    calib = dataset_pb2.LaserCalibration(beam_inclination_min=-0.4, beam_inclination_max=0.1)
    if explicit:
        calib.beam_inclinations.extend(np.sort(rng.uniform(-0.4, 0.1, H)).tolist())
    incl_asc = np.asarray(calib.beam_inclinations) if explicit else -0.4 + (np.arange(H) + 0.5) / H * 0.5
    E = _random_transform(rng)
    E[:3, :3] = E[:3, :3] @ rangeimage.euler_to_rotmat(np.array(0.0), np.array(0.0), np.array(2.5))  # large yaw
    vehicle = _random_transform(rng, angles=np.pi, shift=5000.0)  # global coordinates are large
    post = np.linalg.inv(vehicle) @ _random_transform(rng, angles=0.2, shift=3.0)
    pixel_pose = None
    if with_pixel_pose:
        pixel_pose = np.zeros((H, W, 6), np.float32)
        pixel_pose[..., :3] = rng.uniform(-np.pi, np.pi, (H, W, 3))  # any rotation per pixel
        pixel_pose[..., 3:] = rng.uniform(-1000.0, 1000.0, (H, W, 3))
    got, pix = rangeimage.range_image_to_points(ranges, rangeimage.row_inclinations(calib, H), E, vehicle,
                                                pixel_pose, post)
    ref = brute_force_points(ranges, incl_asc, E, vehicle, pixel_pose, post)
    assert got.shape == ref.shape == ((ranges > 0).sum(), 3)
    assert got.dtype == np.float64
    scale = max(1.0, np.abs(ref).max())
    assert np.abs(got - ref).max() < 1e-12 * scale * 100  # float64 round-off only
    assert (ranges[pix[:, 0], pix[:, 1]] > 0).all()


def test_row_order_and_uniform_inclinations():
    calib = dataset_pb2.LaserCalibration(beam_inclination_min=-0.3, beam_inclination_max=0.1)
    rows = rangeimage.row_inclinations(calib, 4)
    assert np.allclose(rows, [0.05, -0.05, -0.15, -0.25])  # row 0 is the highest beam
    calib.beam_inclinations.extend([-0.3, -0.2, 0.0, 0.1])
    assert np.allclose(rangeimage.row_inclinations(calib, 4), [0.1, 0.0, -0.2, -0.3])
    with pytest.raises(RangeImageError, match="4 beam_inclinations for a range image of 5 rows"):
        rangeimage.row_inclinations(calib, 5)
    # column 0 looks backwards-left (azimuth just below +pi), the middle ones forward
    az = rangeimage.column_azimuths(8)
    assert np.isclose(az[0], np.pi - np.pi / 8) and np.isclose(az[3], np.pi / 8) and np.isclose(az[4], -np.pi / 8)


def test_euler_conventions():
    rng = np.random.default_rng(0)
    r, p, y = rng.uniform(-1, 1, 3)
    R = rangeimage.euler_to_rotmat(np.array(r), np.array(p), np.array(y))
    ref = np.array(_matmul(_mat_rz(y), _matmul(_mat_ry(p), _mat_rx(r))))
    assert np.allclose(R, ref, atol=1e-15)
    assert np.allclose(rangeimage.rotmat_to_euler(R), (r, p, y))
    v = rng.normal(size=(5, 3))
    assert np.allclose(rangeimage.rotate_euler(v, np.full(5, r), np.full(5, p), np.full(5, y)), v @ R.T)


# ----------------------------------------------------------------------------- matrices
def test_matrix_round_trip_and_protobuf_agreement():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(5, 9, 4)).astype(np.float32)
    blob = rangeimage.encode_matrix_float(a)
    out = rangeimage.decode_matrix_float(blob)
    assert out.dtype == np.float32 and out.shape == a.shape and np.array_equal(out, a)
    out[0, 0, 0] = 1.0  # writable, own memory
    # the hand-written packed field is what the generated class reads, and vice versa
    msg = dataset_pb2.MatrixFloat.FromString(zlib.decompress(blob))
    assert list(msg.shape.dims) == [5, 9, 4] and np.array_equal(np.array(msg.data, np.float32), a.ravel())
    assert np.array_equal(rangeimage.decode_matrix_float(zlib.compress(msg.SerializeToString())), a)


def test_matrix_unpacked_encoding_takes_the_generic_path():
    # Non-packed repeated floats (tag 0x0d per value) are valid protobuf too.
    vals = np.arange(6, dtype=np.float32)
    raw = b"".join(b"\x0d" + v.tobytes() for v in vals)
    raw += b"\x12" + bytes([len(s := dataset_pb2.MatrixShape(dims=[2, 3]).SerializeToString())]) + s
    assert np.array_equal(rangeimage.decode_matrix_float(zlib.compress(raw)), vals.reshape(2, 3))


def test_matrix_errors():
    with pytest.raises(RangeImageError, match="not zlib-compressed"):
        rangeimage.decode_matrix_float(b"garbage")
    bad = dataset_pb2.MatrixFloat(data=[1.0, 2.0, 3.0])
    bad.shape.dims.extend([2, 2])
    with pytest.raises(RangeImageError, match="holds 3 values but its shape is \\[2, 2\\]"):
        rangeimage.decode_matrix_float(zlib.compress(bad.SerializeToString()))
    with pytest.raises(RangeImageError, match="not a serialized MatrixFloat"):
        rangeimage.decode_matrix_float(zlib.compress(b"\x0a\xff\xff\xff\xff\x0f"))


# ----------------------------------------------------------------------------- writing
def test_points_to_range_images_round_trip():
    rng = np.random.default_rng(2)
    H, W = 5, 64
    beams = np.sort(rng.uniform(-0.3, 0.1, H))
    rows_incl = beams[::-1]
    az = rangeimage.column_azimuths(W)
    i, j = rng.integers(0, H, 300), rng.integers(0, W, 300)
    key = np.unique(i * W + j, return_index=True)[1]
    i, j = i[key], j[key]
    r = rng.uniform(1, 60, len(i))
    pts = np.stack([r * np.cos(rows_incl[i]) * np.cos(az[j]), r * np.cos(rows_incl[i]) * np.sin(az[j]),
                    r * np.sin(rows_incl[i])], 1)
    # a second and a third point behind some of them (farther along the same ray)
    extra = np.concatenate([pts[:10] * 1.5, pts[:3] * 2.0])
    first, second, dropped = rangeimage.points_to_range_images(np.concatenate([pts, extra]), beams, W)
    assert dropped == 3
    assert np.allclose(first[i, j], r, rtol=1e-6) and (first > 0).sum() == len(i)
    assert (second > 0).sum() == 10 and np.allclose(second[i[:10], j[:10]], 1.5 * r[:10], rtol=1e-6)
    back, _ = rangeimage.range_image_to_points(first, rows_incl, np.eye(4), np.eye(4))
    order = np.lexsort((j, i))
    assert np.abs(back - pts[order]).max() < 1e-4  # float32 ranges


def test_points_between_columns_never_collide():
    # Azimuths exactly on column boundaries (a sweep offset by half a column) keep one
    # column each, shifted by half a column.
    W = 90
    az = np.deg2rad(np.arange(0.0, 360.0, 4.0))
    pts = np.stack([10 * np.cos(az), 10 * np.sin(az), np.zeros_like(az)], 1)
    first, second, dropped = rangeimage.points_to_range_images(pts, np.array([0.0]), W)
    assert (first > 0).sum() == 90 and (second > 0).sum() == 0 and dropped == 0


def test_cluster_inclinations():
    rng = np.random.default_rng(4)
    beams = np.deg2rad(np.linspace(-25, 10, 32))
    v = np.repeat(beams, 50) + rng.normal(scale=1e-6, size=32 * 50)
    assert np.allclose(rangeimage.cluster_inclinations(v), beams, atol=1e-6)
