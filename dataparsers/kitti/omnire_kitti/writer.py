"""Scene writer ``kitti``: a synthetic scene (``omnire synth``) as one KITTI tracking sequence,
so the reader is tested on scenes where every pose, box and point is known.

Written (``<output>/training/``, sequence 0000), as the tracking release has it::

    image_02/0000/<frame:06d>.png   velodyne/0000/<frame:06d>.bin   calib/0000.txt
    oxts/0000.txt                   label_02/0000.txt
    (<output>/ground_truth.npz/.json: the generator's ground truth, not part of the layout)

- image_02 is the synthetic front camera, *rectified* as KITTI's are: KITTI's rectified
  cameras look level along the car (their labels rotate boxes about the camera's y axis
  only), while the synthetic camera is pitched down, so its image is resampled (bilinear)
  into a level camera at the same centre, zoomed just enough to leave no empty border.
  R_rect is that rotation (unrectified camera 0 = the synthetic camera's orientation).
  image_03 is not written: the generator renders no right stereo camera (P3 is written with
  a KITTI-like baseline all the same, as every calib file has P0-P3).
- Rectified camera 0 sits 6 cm right of image_02 (t_2 = K^-1 P2[:, 3] as on the real rig);
  P matrices use integer pixel centres (cx, cy = ours - 0.5).
- The IMU (ego) frame is the synthetic ego frame; oxts lines hold the ego poses converted to
  latitude / longitude / altitude (inverse of the devkit's Mercator projection, first frame
  in Karlsruhe) and roll / pitch / yaw, with velocities, accelerations (gravity included)
  and yaw rate from finite differences. The Velodyne frame sits at the synthetic LiDAR's
  position with a small mounting yaw; scans are float32 x y z reflectance of the returns
  (rays that came back empty are not stored, as in KITTI), stored in KITTI's order
  (:func:`scan_order`). Generated with
  :data:`HDL64E_LIKE_ELEVATIONS_DEG`, the sweeps have an HDL-64E's 64 uneven beams.
- Labels: boxes present in a frame whose projection meets image_02 (as KITTI labels objects
  seen by the camera); types Car / Pedestrian / Cyclist; track id = actor index; values with
  the release's 6 decimals; truncation 0/1/2 from the share of the 2D box outside the image.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from omnire.api import UNIT_INTENSITY, atomic_write_bytes, atomic_write_text, image_size, read_image, rigid, write_png
from omnire.api import axis_rotation as rot_axis
from omnire_kitti.dataparser import EARTH_RADIUS
from omnire_processed.groundtruth import SyntheticSource

SPLIT, SEQUENCE = "training", "0000"
FIRST_LAT, FIRST_LON, FIRST_ALT = 49.011212804408, 8.4228850417969, 112.83492279053
"""Where frame 0 is placed (a Karlsruhe road, as in tracking sequence 0000)."""
FIRST_YAW = -1.2219096732051
"""Heading of frame 0 (radians, 0 = east, counter-clockwise)."""
CAMERA_T = {0: (0.0, 0.0, 0.0), 1: (-0.5372, 0.0, 0.0), 2: (0.0595, -0.00049, 0.0050), 3: (-0.4725, 0.0033, 0.0045)}
"""t_i = K^-1 P_i[:, 3] (metres): camera i sits at -t_i in rectified camera-0 coordinates (KITTI-like rig)."""
VELODYNE_AXES = rot_axis(2, np.deg2rad(0.4))
"""Velodyne mounting rotation in the IMU frame (x forward, y left, z up, slightly off): a yaw
only, since the synthetic sweeps are cast in the LiDAR's own frame and a tilt would make
each beam's elevation in the Velodyne frame vary with azimuth."""
HDL64E_LIKE_ELEVATIONS_DEG = tuple(float(v) for v in np.round(np.concatenate([
    np.linspace(2.0, -8.33, 32) + 0.04 * np.sin(np.arange(32) * 1.7),  # upper block: ~1/3 degree apart
    np.linspace(-8.87, -24.8, 32) + 0.05 * np.cos(np.arange(32) * 2.3),  # lower block: ~1/2 degree apart
]), 3))
"""64 uneven beam elevations (degrees) laid out like an HDL-64E's two blocks, with a per-laser
offset as a unit's own calibration has: ``omnire synth --lidar-elevations-deg`` casts the
synthetic sweeps with them (tests/test_kitti_reader.py)."""
TYPE_OF_KIND = {"car": "Car", "pedestrian": "Pedestrian", "cyclist": "Cyclist"}
GRAVITY = 9.80665


def write_scene(source: Path, output: Path) -> None:
    """Scene-writer entry point (``omnire synth --format kitti``)."""
    write_kitti(source, output)


def write_kitti(source: Path, output: Path) -> dict:
    """Write the synthetic scene in ``source`` into the empty folder ``output`` (layout in the
    module docstring). Returns a summary with the written calibration."""
    src = SyntheticSource.load(Path(source))
    split = Path(output) / SPLIT
    F = src.num_frames
    cam = src.scene.cameras[0]
    W, H = cam.width, cam.height
    cam_to_ego = src.cam_to_ego[0]
    # Level rectified frame: OpenCV axes with z along the camera's horizontal forward direction.
    fwd = cam_to_ego[:3, 2].copy()
    fwd[2] = 0.0
    fwd /= np.linalg.norm(fwd)
    down = np.array([0.0, 0.0, -1.0])
    R_rect_in_ego = np.column_stack([np.cross(down, fwd), down, fwd])  # columns: x right, y down, z forward
    t = {i: np.asarray(v, dtype=np.float64) for i, v in CAMERA_T.items()}
    rect_to_ego = rigid(R_rect_in_ego, cam_to_ego[:3, 3] + R_rect_in_ego @ t[2])
    R_src_from_rect = cam_to_ego[:3, :3].T @ R_rect_in_ego
    K_src = src.K[0]
    K_rect = K_src.copy()
    K_rect[:2, :2] *= _zoom_to_fill(K_src, R_src_from_rect, W, H)
    K_file = K_rect.copy()
    K_file[0, 2] -= 0.5  # KITTI: pixel centres at integers
    K_file[1, 2] -= 0.5
    P = {i: K_file @ np.column_stack([np.eye(3), t[i]]) for i in range(4)}
    R_rect = R_src_from_rect.T  # unrectified camera 0 (the synthetic camera) -> rectified
    velo_to_ego = rigid(VELODYNE_AXES, src.lidar_to_ego[:3, 3])
    R4 = rigid(R_rect)
    Tr_velo_cam = R4.T @ np.linalg.inv(rect_to_ego) @ velo_to_ego
    Tr_imu_velo = np.linalg.inv(velo_to_ego)
    calib = [f"P{i}: " + _fmt(P[i].ravel()) for i in range(4)]
    calib += ["R_rect " + _fmt(R_rect.ravel()), "Tr_velo_cam " + _fmt(Tr_velo_cam[:3].ravel()),
              "Tr_imu_velo " + _fmt(Tr_imu_velo[:3].ravel())]
    atomic_write_text(split / "calib" / f"{SEQUENCE}.txt", "\n".join(calib) + "\n")

    mercator_from_gen = _mercator_from_generator(src.ego[0])
    atomic_write_text(split / "oxts" / f"{SEQUENCE}.txt", _oxts_lines(mercator_from_gen[None] @ src.ego, src.times))

    for f in range(F):
        path = Path(cam.image_paths[f])
        img = read_image(path, *image_size(path))  # (H, W, 3) uint8
        write_png(split / "image_02" / SEQUENCE / f"{f:06d}.png", rectify(img, K_src, K_rect, R_src_from_rect) / 255.0)
        velo_to_gen = src.ego[f] @ velo_to_ego
        p = (src.points(f) - velo_to_gen[:3, 3]) @ velo_to_gen[:3, :3]  # (N, 3) Velodyne frame
        refl = src.intensity[f] if src.intensity[f] is not None else np.zeros(len(p))
        order = scan_order(p)
        p, refl = p[order], np.asarray(refl)[order]
        atomic_write_bytes(split / "velodyne" / SEQUENCE / f"{f:06d}.bin",
                           np.column_stack([p, UNIT_INTENSITY.from_unit(refl)]).astype("<f4").tobytes())
    atomic_write_text(split / "label_02" / f"{SEQUENCE}.txt", _labels(src, rect_to_ego, P[2], W, H))
    src.save_ground_truth(Path(output), mercator_from_gen,
                          "KITTI tracking layout (training/0000); file_from_generator maps to the Mercator frame of "
                          "the oxts poses (x east, y north, z altitude)")
    return {"frames": F, "P2": P[2], "R_rect": R_rect, "K_rect": K_rect, "rect_to_ego": rect_to_ego,
            "velo_to_ego": velo_to_ego, "mercator_from_generator": mercator_from_gen}


def scan_order(points_velodyne: np.ndarray, gap_deg: float = 0.05) -> np.ndarray:
    """(N, 3) returns of a sweep cast from the optical centre -> (N,) the order KITTI stores a
    scan in: laser by laser from the top one, each laser's returns by increasing azimuth from
    behind the car. A laser's returns share one elevation here, so lasers are the elevation
    clusters (a gap above ``gap_deg`` between sorted elevations starts a new one)."""
    az = np.arctan2(points_velodyne[:, 1], points_velodyne[:, 0])
    el = np.rad2deg(np.arctan2(points_velodyne[:, 2], np.hypot(points_velodyne[:, 0], points_velodyne[:, 1])))
    by_el = np.argsort(-el, kind="stable")
    laser = np.empty(len(el), dtype=np.int64)
    laser[by_el] = np.concatenate([[0], np.cumsum(-np.diff(el[by_el]) > gap_deg)]) if len(el) else []
    return np.lexsort((az, laser))


def _fmt(values) -> str:
    return " ".join(f"{v:.12e}" for v in values)


# ----------------------------------------------------------------------------- image
def rectify(img: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray, R_src_from_dst: np.ndarray) -> np.ndarray:
    """The image (H, W, 3) uint8 seen by pinhole ``K_src`` resampled (bilinear) into a camera
    at the same centre with ``K_dst`` turned by ``R_src_from_dst`` (dst -> src camera axes).
    Both K with pixel centres at +0.5. Returns (H, W, 3) uint8."""
    H, W = img.shape[:2]
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xs, ys = _map_pixels(u.ravel(), v.ravel(), K_src, K_dst, R_src_from_dst)
    x, y = np.clip(xs - 0.5, 0, W - 1), np.clip(ys - 0.5, 0, H - 1)  # array coordinates
    x0, y0 = np.minimum(x.astype(int), W - 2), np.minimum(y.astype(int), H - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    im = img.astype(np.float64)
    out = (im[y0, x0] * (1 - fx) * (1 - fy) + im[y0, x0 + 1] * fx * (1 - fy)
           + im[y0 + 1, x0] * (1 - fx) * fy + im[y0 + 1, x0 + 1] * fx * fy)
    return np.clip(np.round(out), 0, 255).astype(np.uint8).reshape(H, W, -1)


def _map_pixels(u, v, K_src, K_dst, R_src_from_dst) -> tuple[np.ndarray, np.ndarray]:
    """Destination pixels (u, v) (M,) -> source pixel coordinates (M,), both +0.5 convention."""
    rays = np.stack([(u - K_dst[0, 2]) / K_dst[0, 0], (v - K_dst[1, 2]) / K_dst[1, 1], np.ones_like(u)], 1)
    s = rays @ R_src_from_dst.T
    return K_src[0, 0] * s[:, 0] / s[:, 2] + K_src[0, 2], K_src[1, 1] * s[:, 1] / s[:, 2] + K_src[1, 2]


def _zoom_to_fill(K: np.ndarray, R_src_from_dst: np.ndarray, W: int, H: int) -> float:
    """Smallest focal-length factor (>= 1) for which every destination pixel centre maps
    inside the source image's pixel centres (no border to invent)."""
    u = np.concatenate([np.arange(W) + 0.5, np.arange(W) + 0.5, np.full(H, 0.5), np.full(H, W - 0.5)])
    v = np.concatenate([np.full(W, 0.5), np.full(W, H - 0.5), np.arange(H) + 0.5, np.arange(H) + 0.5])

    def inside(s: float) -> bool:
        Kd = K.copy()
        Kd[:2, :2] *= s
        xs, ys = _map_pixels(u, v, K, Kd, R_src_from_dst)
        return bool((xs >= 0.5 - 1e-9).all() and (xs <= W - 0.5 + 1e-9).all()
                    and (ys >= 0.5 - 1e-9).all() and (ys <= H - 0.5 + 1e-9).all())

    lo, hi = 1.0, 1.0
    while not inside(hi):
        lo, hi = hi, hi * 1.25
        if hi > 10:
            raise ValueError("the camera is turned too far from level to rectify")
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if inside(mid) else (mid, hi)
    return hi


# ----------------------------------------------------------------------------- oxts
def _mercator_from_generator(ego0: np.ndarray) -> np.ndarray:
    """(4, 4) generator world -> Mercator frame: frame 0 at FIRST_LAT/LON/ALT heading FIRST_YAW."""
    scale = np.cos(np.deg2rad(FIRST_LAT))
    m0 = np.array([scale * FIRST_LON * np.pi * EARTH_RADIUS / 180.0,
                   scale * EARTH_RADIUS * np.log(np.tan((90.0 + FIRST_LAT) * np.pi / 360.0)), FIRST_ALT])
    yaw0 = np.arctan2(ego0[1, 0], ego0[0, 0])
    return rigid(None, m0) @ rigid(rot_axis(2, FIRST_YAW - yaw0)) @ rigid(None, -ego0[:3, 3])


def _oxts_lines(poses: np.ndarray, times: np.ndarray) -> str:
    """(F, 4, 4) IMU-to-Mercator poses at ``times`` (F,) -> the oxts file text (30 values a line)."""
    scale = np.cos(np.deg2rad(FIRST_LAT))
    mx, my, alt = poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3]
    lon = mx * 180.0 / (scale * np.pi * EARTH_RADIUS)
    lat = 360.0 / np.pi * np.arctan(np.exp(my / (scale * EARTH_RADIUS))) - 90.0
    R = poses[:, :3, :3]
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])  # R = Rz(yaw) Ry(pitch) Rx(roll)
    pitch = -np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    if len(times) > 1:
        vel = np.gradient(poses[:, :3, 3], times, axis=0)  # (F, 3) world m/s
        acc = np.gradient(vel, times, axis=0)
        yaw_rate = np.gradient(np.unwrap(yaw), times)
    else:
        vel, acc, yaw_rate = np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1)
    v_body = np.einsum("fji,fj->fi", R, vel)  # forward, left, up
    a_body = np.einsum("fji,fj->fi", R, acc + [0.0, 0.0, GRAVITY])  # accelerometers feel gravity
    lines = []
    for f in range(len(poses)):
        vals = [lat[f], lon[f], alt[f], roll[f], pitch[f], yaw[f], vel[f, 1], vel[f, 0], *v_body[f],
                *a_body[f], *a_body[f], 0.0, 0.0, yaw_rate[f], 0.0, 0.0, yaw_rate[f]]
        lines.append(" ".join(repr(float(v)) for v in vals) + " 0.02 0.02 4 10 4 4 0")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- labels
def _labels(src: SyntheticSource, rect_to_ego: np.ndarray, P2: np.ndarray, W: int, H: int) -> str:
    """label_02 text: boxes of the actors present in each frame that image_02 sees."""
    corners_unit = np.array([[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5) for sz in (-0.5, 0.5)])
    lines = []
    for f in range(src.num_frames):
        gen_to_rect = np.linalg.inv(src.ego[f] @ rect_to_ego)
        for i, kind in enumerate(src.kinds):
            if not src.present[i, f]:
                continue
            box = gen_to_rect @ src.boxes[i, f]  # (4, 4) box -> rectified camera 0
            if np.abs(box[:3, 2] - [0.0, -1.0, 0.0]).max() > 1e-6:
                raise ValueError(f"actor {src.track_ids[i]} frame {f}: box not upright in the rectified camera "
                                 "frame; KITTI labels rotate boxes about the camera y axis only")
            l, w, h = (float(v) for v in src.sizes[i])
            c = box[:3, 3]
            corners = (corners_unit * [l, w, h]) @ box[:3, :3].T + c  # (8, 3)
            front = corners[:, 2] > 0.1
            if c[2] <= 0.5 or not front.any():
                continue
            uv = corners[front] @ P2[:, :3].T + P2[:, 3]
            uv = uv[:, :2] / uv[:, 2:]
            x1, y1 = uv.min(0)
            x2, y2 = uv.max(0)
            cx1, cy1, cx2, cy2 = max(x1, 0.0), max(y1, 0.0), min(x2, W - 1.0), min(y2, H - 1.0)
            if cx2 <= cx1 or cy2 <= cy1:
                continue  # not in the image
            area = (x2 - x1) * (y2 - y1)
            outside = 1.0 - (cx2 - cx1) * (cy2 - cy1) / area if area > 0 else 0.0
            trunc = 0 if outside < 0.1 and front.all() else (1 if outside < 0.5 else 2)
            ry = float(np.arctan2(-box[2, 0], box[0, 0]))  # heading (cos ry, 0, -sin ry)
            loc = c + [0.0, h / 2.0, 0.0]  # bottom centre (camera y points down)
            alpha = (ry - np.arctan2(loc[0], loc[2]) + np.pi) % (2 * np.pi) - np.pi
            lines.append(f"{f} {i} {TYPE_OF_KIND[str(kind)]} {trunc} 0 {alpha:.6f} {cx1:.6f} {cy1:.6f} {cx2:.6f} "
                         f"{cy2:.6f} {h:.6f} {w:.6f} {l:.6f} {loc[0]:.6f} {loc[1]:.6f} {loc[2]:.6f} {ry:.6f}")
    return "\n".join(lines) + ("\n" if lines else "")
