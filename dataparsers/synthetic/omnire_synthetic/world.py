"""Procedural street, ego motion and actors with exact trajectories (generator world frame).

Generator world: z up, metres, the street runs along +x with its centre line at y = 0;
vehicles drive on the right (the ego's lanes have y < 0). Everything is drawn from one
``numpy.random.Generator`` so a seed fixes the scene.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from omnire.api import rigid
from omnire_body import lbs
from omnire_body.lbs import LBSOutput
from omnire_body.motion import gait_pose
from omnire_body.rest import BODY_TO_BOX
from omnire_body.template import BodyTemplate
from omnire_synthetic.meshes import Mesh, box, ellipsoid, prism, quad, rot_x, rot_z
from omnire_synthetic.textures import FACADES, MAT, PAINTS, PANTS, SHIRTS


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """What a preset puts in the street."""

    lanes_per_dir: int = 2
    lane_width: float = 3.5
    sidewalk_width: float = 3.5
    buildings: bool = True
    highway: bool = False
    ego_speed: float = 7.0
    cars_same: int = 3
    cars_oncoming: int = 3
    cars_parked: int = 4
    walkers: int = 4
    crossers: int = 2
    cyclists: int = 1
    tree_spacing: float = 14.0
    pole_spacing: float = 25.0
    crossing_ahead: float = 22.0
    """Distance (m) ahead of the ego's start where pedestrians cross (plus 60% of its travel)."""


PRESETS: dict[str, SceneSpec] = {
    "urban": SceneSpec(),
    "highway": SceneSpec(
        lanes_per_dir=3, sidewalk_width=0.0, buildings=False, highway=True, ego_speed=16.0,
        cars_same=6, cars_oncoming=6, cars_parked=0, walkers=0, crossers=0, cyclists=0,
        tree_spacing=0.0, pole_spacing=40.0,
    ),
    "crowd": SceneSpec(
        ego_speed=2.5, cars_same=0, cars_oncoming=0, cars_parked=3, walkers=10, crossers=16, cyclists=0,
        crossing_ahead=11.0,
    ),
    "empty": SceneSpec(cars_same=0, cars_oncoming=0, cars_parked=0, walkers=0, crossers=0, cyclists=0),
}


@dataclasses.dataclass
class Actor:
    """One actor with exact per-frame state.

    poses: (F, 4, 4) box-to-world; size (3,) l, w, h; present (F,) bool. Pedestrians also
    carry body_pose (F, 23, 3, 3), global_orient (F, 3, 3) body-to-world and transl (F, 3)
    (SMPL convention: rotation about the pelvis joint, then translation); cyclists a pedal
    phase (F,).
    """

    track_id: str
    kind: str  # "car" | "pedestrian" | "cyclist"
    poses: np.ndarray
    size: np.ndarray
    present: np.ndarray
    stationary: bool = False
    mesh: Optional[Mesh] = None  # box-local mesh for rigid actors
    body_pose: Optional[np.ndarray] = None
    global_orient: Optional[np.ndarray] = None
    transl: Optional[np.ndarray] = None
    body_verts: Optional[np.ndarray] = None  # (F, V, 3) float32 world vertices (pedestrians)
    body_mats: Optional[np.ndarray] = None  # (F_faces,) materials of the body faces
    phase: Optional[np.ndarray] = None
    colors: tuple[int, ...] = ()

    def mesh_at(self, t: int, template: Optional[BodyTemplate] = None) -> Mesh:
        """World-space mesh at frame t."""
        if self.kind == "pedestrian":
            assert template is not None and self.body_verts is not None
            return Mesh(self.body_verts[t].astype(np.float64), template.faces, _body_uv(template), self.body_mats)
        local = self.mesh if self.kind == "car" else cyclist_mesh(float(self.phase[t]), self.colors)
        return local.transformed(self.poses[t])


def _pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    return rigid(rot_z(yaw), (x, y, z))


def _heading_poses(xy: np.ndarray, z: float, times: np.ndarray, fixed_yaw: Optional[float] = None) -> np.ndarray:
    """Box poses (F, 4, 4) along an xy path (F, 2), heading along the path's derivative."""
    if fixed_yaw is None:
        vel = np.gradient(xy, times, axis=0) if len(times) > 1 else np.array([[1.0, 0.0]])
        yaw = np.arctan2(vel[:, 1], vel[:, 0])
    else:
        yaw = np.full(len(times), fixed_yaw)
    return np.stack([_pose(p[0], p[1], z, a) for p, a in zip(xy, yaw)])


# ----------------------------------------------------------------------------- ego

def ego_trajectory(spec: SceneSpec, times: np.ndarray) -> np.ndarray:
    """Ego-to-world (F, 4, 4): the ego drives +x in the inner right lane with a gentle weave.
    Ego frame: x forward, y left, z up, origin on the ground under the vehicle centre."""
    x = spec.ego_speed * times
    y = -spec.lane_width / 2 + 0.25 * np.sin(0.5 * times)
    xy = np.stack([x, y], 1)
    if len(times) > 1:
        vel = np.stack([np.full_like(times, spec.ego_speed), 0.125 * np.cos(0.5 * times)], 1)
    else:
        vel = np.array([[1.0, 0.0]])
    yaw = np.arctan2(vel[:, 1], vel[:, 0])
    return np.stack([_pose(p[0], p[1], 0.0, a) for p, a in zip(xy, yaw)])


CAMERA_LAYOUT = (
    ("front_camera", 0.0, (1.6, 0.0, 1.6)),
    ("front_left_camera", 50.0, (1.5, 0.3, 1.6)),
    ("front_right_camera", -50.0, (1.5, -0.3, 1.6)),
    ("left_camera", 100.0, (0.5, 0.9, 1.6)),
    ("right_camera", -100.0, (0.5, -0.9, 1.6)),
    ("back_camera", 180.0, (-2.0, 0.0, 1.6)),
)
LIDAR_HEIGHT = 1.9


def camera_rigs(num_cameras: int, width: int, height: int, pitch_deg: float = -3.0):
    """(names, cam_to_ego (C, 4, 4) OpenCV axes, K (C, 3, 3)) for the first ``num_cameras``."""
    from omnire_synthetic.render import look_rotation

    names, c2e, Ks = [], [], []
    p = np.deg2rad(pitch_deg)
    for name, yaw_deg, pos in CAMERA_LAYOUT[:num_cameras]:
        y = np.deg2rad(yaw_deg)
        fwd = np.array([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)])
        names.append(name)
        c2e.append(rigid(look_rotation(fwd), pos))
        f = 0.85 * width
        Ks.append(np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]]))
    return names, np.stack(c2e), np.stack(Ks)


# ----------------------------------------------------------------------------- static street

def build_static(spec: SceneSpec, rng: np.random.Generator, x0: float, x1: float) -> Mesh:
    """Road with markings, sidewalks with curbs, facades, trees and poles over x in [x0, x1]."""
    parts: list[Mesh] = []
    half = spec.lanes_per_dir * spec.lane_width
    tile = 8.0
    nx = max(1, int(np.ceil((x1 - x0) / tile)))
    # Road surface, split per lane and in 8 m tiles (keeps triangles small near the cameras).
    for k in range(-spec.lanes_per_dir, spec.lanes_per_dir):
        ya, yb = k * spec.lane_width, (k + 1) * spec.lane_width
        parts.append(quad([(x0, ya, 0), (x1, ya, 0), (x1, yb, 0), (x0, yb, 0)], MAT["asphalt"], (4.0, 4.0), nu=nx))
    mz = 0.005  # markings float 5 mm above the asphalt
    # Centre line: double yellow (solid).
    for off in (-0.12, 0.12):
        parts.append(quad([(x0, off - 0.06, mz), (x1, off - 0.06, mz), (x1, off + 0.06, mz), (x0, off + 0.06, mz)],
                          MAT["marking_yellow"], (1.0, 1.0), nu=nx))
    # Lane dividers: 3 m dashes every 9 m; edge lines solid.
    for side in (-1, 1):
        for k in range(1, spec.lanes_per_dir):
            yc = side * k * spec.lane_width
            for xs in np.arange(x0, x1, 9.0):
                parts.append(quad([(xs, yc - 0.07, mz), (xs + 3.0, yc - 0.07, mz), (xs + 3.0, yc + 0.07, mz),
                                   (xs, yc + 0.07, mz)], MAT["marking"], (1.0, 1.0)))
        ye = side * (half - 0.3)
        parts.append(quad([(x0, ye - 0.08, mz), (x1, ye - 0.08, mz), (x1, ye + 0.08, mz), (x0, ye + 0.08, mz)],
                          MAT["marking"], (1.0, 1.0), nu=nx))
    if not spec.highway:
        # A zebra crossing 30 m ahead of the start.
        for k in range(int(2 * half / 1.0)):
            yc = -half + 0.5 + k * 1.0
            if abs(yc) < 0.3:
                continue
            parts.append(quad([(28.0, yc - 0.25, mz), (32.0, yc - 0.25, mz), (32.0, yc + 0.25, mz),
                               (28.0, yc + 0.25, mz)], MAT["marking"], (1.0, 1.0)))
    curb_h = 0.15
    for side in (-1, 1):
        if spec.sidewalk_width > 0:
            yi, yo = side * half, side * (half + spec.sidewalk_width)
            lo, hi = sorted((yi, yo))
            parts.append(quad([(x0, lo, curb_h), (x1, lo, curb_h), (x1, hi, curb_h), (x0, hi, curb_h)],
                              MAT["paving"], (1.0, 1.0), nu=nx))
            parts.append(quad([(x0, yi, 0.0), (x1, yi, 0.0), (x1, yi, curb_h), (x0, yi, curb_h)],
                              MAT["curb"], (1.0, 1.0), nu=nx))
        outer = side * (half + spec.sidewalk_width)
        if spec.buildings:
            parts += _building_row(rng, side, outer, x0, x1, curb_h)
        else:
            # Grass verge and, on a highway, a noise wall.
            lo, hi = sorted((outer, outer + side * 6.0))
            gz = curb_h if spec.sidewalk_width > 0 else 0.0
            parts.append(quad([(x0, lo, gz), (x1, lo, gz), (x1, hi, gz), (x0, hi, gz)], MAT["grass"], (3.0, 3.0), nu=nx))
            if spec.highway:
                yw = outer + side * 6.0
                parts.append(quad([(x0, yw, 4.0), (x1, yw, 4.0), (x1, yw, 0.0), (x0, yw, 0.0)], MAT["noise_wall"],
                                  (4.0, 4.0), nu=nx))
        if spec.tree_spacing > 0:
            yt = side * (half + min(1.0, spec.sidewalk_width / 2))
            for xt in np.arange(x0 + rng.uniform(0, spec.tree_spacing), x1, spec.tree_spacing):
                parts.append(_tree(rng).transformed(rigid(None, (xt + rng.uniform(-2, 2), yt, curb_h))))
        if spec.pole_spacing > 0:
            yp = side * (half + 0.4)
            for xp in np.arange(x0 + rng.uniform(0, spec.pole_spacing), x1, spec.pole_spacing):
                parts.append(_pole(side).transformed(rigid(None, (xp, yp, curb_h if spec.sidewalk_width else 0.0))))
    if spec.highway:
        # Concrete median barrier.
        parts.append(box((x1 - x0, 0.5, 0.9), MAT["barrier"], uv_size=1.0).transformed(
            rigid(None, ((x0 + x1) / 2, 0.0, 0.45))))
    return Mesh.concat(parts)


def _building_row(rng, side: int, y_front: float, x0: float, x1: float, z0: float) -> list[Mesh]:
    parts = []
    x = x0 - rng.uniform(0, 8)
    while x < x1:
        w = rng.uniform(8.0, 18.0)
        h = rng.choice([6.0, 9.0, 12.0, 15.0, 18.0, 24.0])
        depth = 12.0
        setback = rng.uniform(0.0, 1.5)
        mat = int(rng.choice(FACADES))
        yc = y_front + side * (setback + depth / 2)
        b = box((w, depth, h), {"side": mat, "top": MAT["curb"]}, facade_uv=(3.0, 3.0))
        parts.append(b.transformed(rigid(None, (x + w / 2, yc, z0 + h / 2))))
        x += w + (rng.uniform(1.0, 5.0) if rng.random() < 0.3 else 0.0)
    return parts


def _tree(rng) -> Mesh:
    h = rng.uniform(2.2, 3.0)
    r = rng.uniform(1.3, 2.0)
    trunk = prism(0.14, h + 0.5, MAT["trunk"], n=8, uv_size=(0.5, 1.0))
    crown = ellipsoid((r, r, r * 1.15), MAT["foliage"], n_lat=8, n_lon=12, uv_size=1.2)
    return Mesh.concat([trunk, crown.transformed(rigid(rot_z(rng.uniform(0, 6.28)), (0.0, 0.0, h + r * 0.9)))])


def _pole(side: int) -> Mesh:
    pole = prism(0.09, 7.0, MAT["metal"], n=6, uv_size=(0.5, 2.0))
    arm = box((0.12, 1.8, 0.12), MAT["metal"]).transformed(rigid(None, (0.0, -side * 0.9, 6.9)))
    lamp = box((0.5, 0.35, 0.15), MAT["marking"]).transformed(rigid(None, (0.0, -side * 1.7, 6.8)))
    return Mesh.concat([pole, arm, lamp])


# ----------------------------------------------------------------------------- actors

def car_mesh(size: np.ndarray, paint: int) -> Mesh:
    """Box-local car: body, cabin with glass, four wheels. Origin at the box centre, x forward."""
    l, w, h = size
    z_bottom = -h / 2
    wheel_r = 0.33
    body_h = 0.55 * h - 0.12
    body = box((l, w, body_h), paint, uv_size=2.0).transformed(rigid(None, (0.0, 0.0, z_bottom + 0.2 + body_h / 2)))
    cab_h = h - 0.2 - body_h
    cab = box((0.52 * l, 0.9 * w, cab_h), {"side": MAT["glass"], "top": paint}, uv_size=1.5).transformed(
        rigid(None, (-0.06 * l, 0.0, z_bottom + 0.2 + body_h + cab_h / 2)))
    wheels = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            wheel = prism(wheel_r, 0.22, MAT["tire"], n=10, cap_mat=MAT["metal"], uv_size=(0.5, 0.5))
            wheel = wheel.transformed(rigid(rot_x(np.pi / 2), (0.0, 0.11, 0.0)))  # axis along y
            wheels.append(wheel.transformed(rigid(None, (sx * 0.33 * l, sy * (w / 2 - 0.05), z_bottom + wheel_r))))
    lights = [box((0.05, 0.3, 0.12), MAT["marking"]).transformed(rigid(None, (l / 2, sy * (w / 2 - 0.3), z_bottom + 0.2 + body_h * 0.7)))
              for sy in (-1, 1)]
    return Mesh.concat([body, cab] + wheels + lights)


CYCLIST_SIZE = np.array([1.8, 0.7, 1.75])


def cyclist_mesh(phase: float, colors: tuple[int, ...]) -> Mesh:
    """Box-local bicycle and rider at pedal phase ``phase`` (radians); non-rigid: the legs
    pedal and the wheels turn. Origin at the box centre (ground at z = -h/2), x forward."""
    zg = -CYCLIST_SIZE[2] / 2
    shirt, pants = colors if colors else (SHIRTS[0], PANTS[0])
    parts = []
    r = 0.34
    for xw in (-0.55, 0.55):
        wheel = prism(r, 0.05, MAT["tire"], n=12, cap_mat=MAT["spokes"], uv_size=(0.5, 0.5))
        # Spin the wheel about its axle so the spoke texture rotates with the phase.
        wheel = wheel.transformed(rigid(rot_x(np.pi / 2) @ rot_z(-phase * 1.6), (0.0, 0.025, 0.0)))
        parts.append(wheel.transformed(rigid(None, (xw, 0.0, zg + r))))
    crank = np.array([0.0, 0.0, zg + r])
    frame_bars = [((-0.55, zg + r), (0.0, zg + r)), ((0.0, zg + r), (-0.15, zg + 0.95)),
                  ((-0.15, zg + 0.95), (0.45, zg + 0.95)), ((0.45, zg + 0.95), (0.55, zg + r)),
                  ((-0.55, zg + r), (-0.15, zg + 0.95)), ((0.0, zg + r), (0.45, zg + 0.95))]
    for (xa, za), (xb, zb) in frame_bars:
        parts.append(_bar(np.array([xa, 0.0, za]), np.array([xb, 0.0, zb]), 0.035, MAT["bike"]))
    parts.append(_bar(np.array([0.45, -0.25, zg + 1.05]), np.array([0.45, 0.25, zg + 1.05]), 0.03, MAT["metal"]))
    hip = np.array([-0.15, 0.0, zg + 1.0])
    shoulder = np.array([0.2, 0.0, zg + 1.5])
    parts.append(_bar(hip, shoulder, 0.17, shirt))
    parts.append(ellipsoid((0.11, 0.1, 0.13), MAT["skin"], n_lat=6, n_lon=8).transformed(
        rigid(None, shoulder + np.array([0.08, 0.0, 0.2]))))
    for sy in (-1, 1):
        parts.append(_bar(shoulder + [0, sy * 0.18, 0], np.array([0.45, sy * 0.22, zg + 1.05]), 0.045, shirt))
        # Pedal on a 0.17 m crank; knee found from thigh/shin lengths (planar two-link IK).
        a = phase + (0.0 if sy > 0 else np.pi)
        pedal = crank + np.array([0.17 * np.cos(a), sy * 0.12, 0.17 * np.sin(a)])
        h = hip + np.array([0.0, sy * 0.12, 0.0])
        d = pedal - h
        dist = np.linalg.norm(d)
        l1 = l2 = 0.45
        dist_c = min(dist, l1 + l2 - 1e-3)
        along = d / dist
        perp = np.array([along[2], 0.0, -along[0]])  # knee bends forward (+x side)
        if perp[0] < 0:
            perp = -perp
        x = dist_c / 2
        knee = h + along * x + perp * np.sqrt(max(l1**2 - x**2, 0.0))
        parts.append(_bar(h, knee, 0.07, pants))
        parts.append(_bar(knee, pedal, 0.055, pants))
    return Mesh.concat(parts)


def _bar(a: np.ndarray, b: np.ndarray, radius: float, mat: int) -> Mesh:
    """A hexagonal prism from a to b."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    L = float(np.linalg.norm(d))
    z = d / max(L, 1e-9)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return prism(radius, L, mat, n=6, uv_size=(0.3, 0.3)).transformed(rigid(np.stack([x, y, z], 1), a))


def body_global_orient(yaw: np.ndarray) -> np.ndarray:
    """(F, 3, 3) canonical-body-to-world rotation for a walker heading ``yaw`` (box x axis)."""
    return np.stack([rot_z(a) @ BODY_TO_BOX for a in yaw])


_BODY_UV_CACHE: dict[int, np.ndarray] = {}


def _body_uv(template: BodyTemplate) -> np.ndarray:
    key = id(template)
    if key not in _BODY_UV_CACHE:
        v = template.vertices
        # Cylindrical UVs around the body axis: texture stripes wrap around the torso.
        _BODY_UV_CACHE[key] = np.stack([np.arctan2(v[:, 0], v[:, 2]) / np.pi * 0.6, v[:, 1] * 2.0], 1)
    return _BODY_UV_CACHE[key]


def body_materials(template: BodyTemplate, shirt: int, pants: int) -> np.ndarray:
    """Face materials from the rest-pose face centre: head/hands skin, torso/arms shirt, legs pants."""
    v = template.vertices
    c = v[template.faces].mean(1)  # (F, 3) canonical: y up, x left
    joints = template.joints
    mats = np.full(len(c), shirt, np.int64)
    mats[c[:, 1] < joints[0, 1] + 0.02] = pants
    mats[c[:, 1] > joints[12, 1] - 0.02] = MAT["skin"]
    mats[np.abs(c[:, 0]) > abs(joints[20, 0]) - 0.02] = MAT["skin"]
    mats[c[:, 1] < joints[7, 1] - 0.03] = MAT["tire"]  # shoes
    return mats


def build_actors(spec: SceneSpec, rng: np.random.Generator, times: np.ndarray, ego: np.ndarray,
                 template: Optional[BodyTemplate], presence_radius: float = 60.0) -> list[Actor]:
    """All actors with exact trajectories; ``ego`` (F, 4, 4) decides presence."""
    F = len(times)
    actors: list[Actor] = []
    half = spec.lanes_per_dir * spec.lane_width
    ego_x0 = float(ego[0, 0, 3])
    dist_travelled = spec.ego_speed * float(times[-1])

    def add(kind: str, poses: np.ndarray, size: np.ndarray, stationary: bool = False, **kw) -> Actor:
        d = np.linalg.norm(poses[:, :2, 3] - ego[:, :2, 3], axis=1)
        present = d < presence_radius
        a = Actor(f"{kind}_{len(actors):03d}", kind, poses, np.asarray(size, float), present, stationary, **kw)
        actors.append(a)
        return a

    def car_size() -> np.ndarray:
        return np.array([rng.uniform(4.0, 4.9), rng.uniform(1.75, 1.95), rng.uniform(1.4, 1.65)])

    for i in range(spec.cars_same):
        lane = i % spec.lanes_per_dir
        y0 = -(lane + 0.5) * spec.lane_width
        # Faster than the ego and starting ahead, so nobody drives through the ego car.
        v = spec.ego_speed * rng.uniform(1.0, 1.2) + rng.uniform(0.5, 2.0)
        x0 = ego_x0 + 12.0 + 14.0 * i + rng.uniform(0, 4)
        x = x0 + v * times
        y = np.full(F, y0)
        if spec.lanes_per_dir > 1 and rng.random() < 0.5:
            # Lane change: a smooth lateral move gives yaw changes to refine.
            target = -((lane + 1) % spec.lanes_per_dir + 0.5) * spec.lane_width
            tc = rng.uniform(0.2, 0.6) * times[-1]
            s = np.clip((times - tc) / 3.0 + 0.5, 0, 1)
            y = y0 + (target - y0) * (3 * s**2 - 2 * s**3)
        size = car_size()
        add("car", _heading_poses(np.stack([x, y], 1), size[2] / 2, times), size,
            mesh=car_mesh(size, int(rng.choice(PAINTS))))
    for i in range(spec.cars_oncoming):
        lane = i % spec.lanes_per_dir
        y0 = (lane + 0.5) * spec.lane_width
        v = spec.ego_speed * rng.uniform(0.9, 1.2) + 1.0
        x0 = ego_x0 + dist_travelled + 25.0 + 18.0 * i + rng.uniform(0, 6)
        x = x0 - v * times
        size = car_size()
        add("car", _heading_poses(np.stack([x, np.full(F, y0)], 1), size[2] / 2, times, fixed_yaw=np.pi), size,
            mesh=car_mesh(size, int(rng.choice(PAINTS))))
    for i in range(spec.cars_parked):
        side = -1 if i % 2 == 0 else 1
        size = car_size()
        x = ego_x0 + 8.0 + 11.0 * i + rng.uniform(0, 3)
        y = side * (half - size[1] / 2 - 0.35)
        yaw = 0.0 if side < 0 else np.pi
        poses = np.repeat(_pose(x, y, size[2] / 2, yaw)[None], F, 0)
        add("car", poses, size, stationary=True, mesh=car_mesh(size, int(rng.choice(PAINTS))))
    for i in range(spec.cyclists):
        y = -(half - 0.9)
        v = rng.uniform(4.0, 5.5)
        x = ego_x0 + 6.0 + 8.0 * i + v * times
        poses = _heading_poses(np.stack([x, np.full(F, y)], 1), CYCLIST_SIZE[2] / 2, times, fixed_yaw=0.0)
        phase = (v * times) / (2 * np.pi * 0.34) * 2 * np.pi / 2.2  # pedal turns per wheel turn
        add("cyclist", poses, CYCLIST_SIZE, phase=phase,
            colors=(int(rng.choice(SHIRTS)), int(rng.choice(PANTS))))
    if template is not None:
        walker_specs = []
        for i in range(spec.walkers):
            side = -1 if i % 2 == 0 else 1
            y = side * (half + spec.sidewalk_width * rng.uniform(0.45, 0.8))
            direction = 1 if rng.random() < 0.5 else -1
            v = rng.uniform(1.0, 1.6)
            x0 = ego_x0 + rng.uniform(8.0, 20.0 + dist_travelled)
            xy = np.stack([x0 + direction * v * times, np.full(F, y)], 1)
            walker_specs.append((xy, 0.0 if direction > 0 else np.pi, 0.15, v))
        for i in range(spec.crossers):
            direction = 1 if i % 2 == 0 else -1
            v = rng.uniform(0.9, 1.5)
            xc = ego_x0 + spec.crossing_ahead + dist_travelled * 0.6 + rng.uniform(0.0, 14.0)
            y0 = -direction * rng.uniform(0.0, half + 1.0)
            y = y0 + direction * v * times
            xy = np.stack([np.full(F, xc), y], 1)
            walker_specs.append((xy, direction * np.pi / 2, None, v))
        for xy, yaw, z_sidewalk, v in walker_specs:
            actors.append(_pedestrian(len(actors), rng, template, xy, yaw, v, times, ego, presence_radius,
                                      z_ground=z_sidewalk))
    return actors


def _pedestrian(index: int, rng, template: BodyTemplate, xy: np.ndarray, yaw: float, speed: float,
                times: np.ndarray, ego: np.ndarray, presence_radius: float, z_ground) -> Actor:
    F = len(times)
    phase = rng.uniform(0, 2 * np.pi) + 2 * np.pi * speed * times / 1.3  # 1.3 m per gait cycle
    body_pose = gait_pose(phase)
    yaws = np.full(F, yaw)
    go = body_global_orient(yaws)  # (F, 3, 3)
    foot = -template.vertices[:, 1].min()  # canonical origin height above the soles
    # Ground under the walker: the sidewalk (15 cm) or the road, decided per frame.
    if z_ground is None:
        zg = np.zeros(F)
    else:
        zg = np.full(F, z_ground)
    centers = np.concatenate([xy, (zg + foot)[:, None]], 1)  # (F, 3) canonical origin in world
    J0 = template.joints[0]
    transl = centers + go @ J0 - J0  # SMPL: world = go @ (v - J0) + J0 + transl = go @ v + centre
    out: LBSOutput = lbs(template, go, body_pose, transl=transl)
    verts = out.vertices.astype(np.float32)  # (F, V, 3)
    poses = np.stack([_pose(c[0], c[1], c[2], a) for c, a in zip(centers, yaws)])
    # Box size: symmetric extent of the posed body about the box centre over all frames.
    local = np.einsum("fij,fvj->fvi", poses[:, :3, :3].transpose(0, 2, 1), verts - centers[:, None].astype(np.float32))
    size = 2.0 * np.abs(local).max(axis=(0, 1))
    d = np.linalg.norm(poses[:, :2, 3] - ego[:, :2, 3], axis=1)
    mats = body_materials(template, int(rng.choice(SHIRTS)), int(rng.choice(PANTS)))
    return Actor(f"pedestrian_{index:03d}", "pedestrian", poses, size, d < presence_radius, False,
                 body_pose=body_pose, global_orient=go, transl=transl, body_verts=verts, body_mats=mats)


def box_mesh_world(actor: Actor, t: int) -> Mesh:
    """The actor's 3D box as a closed mesh at frame t (for coarse dynamic masks)."""
    return box(actor.size, 0, bottom=True).transformed(actor.poses[t])
