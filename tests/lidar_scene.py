"""A small scene whose LiDAR is ray-traced (omnire_synthetic.lidar.cast_sweep, trimesh +
Embree), so a sweep from any pose has an exact answer: a ground plane, a box and a wall,
each of its own reflectivity, seen by a spinning sensor driving along +x, plus one camera
(grey images: the camera loss does not shape the geometry; the LiDAR does)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from omnire.data.scene import BeamModel, CameraSequence, LidarSweeps, SceneData, holdout_split
from omnire.io.images import write_png

LOOK_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
SENSOR_HEIGHT = 1.9
BEAMS = BeamModel(np.linspace(-24.0, 4.0, 16), 1.0, 60.0, 0.5, "test")
REFLECTIVITY = np.array([0.2, 0.8, 0.5])  # ground, box, wall


def _box(lo, hi, material: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.creation.box(extents=np.subtract(hi, lo))
    mesh.apply_translation((np.asarray(lo) + np.asarray(hi)) / 2.0)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), np.full(len(mesh.faces), material)


def world_mesh() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (V, 3), faces (F, 3), material (F,)) of the scene."""
    parts = [_box((-40.0, -40.0, -1.0), (80.0, 40.0, 0.0), 0),  # ground: its top face at z = 0
             _box((9.0, -2.5, 0.0), (11.0, 2.5, 1.8), 1),
             _box((24.0, -20.0, 0.0), (25.0, 20.0, 6.0), 2)]
    verts, faces, mats, offset = [], [], [], 0
    for v, f, m in parts:
        verts.append(v)
        faces.append(f + offset)
        mats.append(m)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(mats)


def sensor_pose(x: float, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = (x, y, SENSOR_HEIGHT)
    return pose


def cast(pose: np.ndarray):
    """The exact sweep (omnire_synthetic.lidar.Sweep) of :data:`BEAMS` from ``pose``."""
    from omnire_synthetic.lidar import LidarSpec, cast_sweep

    verts, faces, mats = world_mesh()
    return cast_sweep(verts, faces, mats, pose, LidarSpec(BEAMS, REFLECTIVITY, 85.0))


def make_lidar_scene(root: Path, frames: int = 6, step_m: float = 0.5, holdout: int = 3) -> SceneData:
    """The scene (module docstring) over ``frames`` frames 0.1 s apart, the sensor moving
    ``step_m`` metres a frame; sweeps carry intensity, times, beams, sensor poses and the
    beam model (so their missing returns are known)."""
    width, height = 32, 24
    K = np.array([[20.0, 0, width / 2], [0, 20.0, height / 2], [0, 0, 1]])
    times = np.arange(frames) * 0.1
    c2w = np.tile(np.eye(4), (frames, 1, 1))
    poses = np.stack([sensor_pose(step_m * f) for f in range(frames)])
    points, intensity, stamps, beams, paths = [], [], [], [], []
    for f in range(frames):
        c2w[f, :3, :3] = LOOK_X
        c2w[f, :3, 3] = (step_m * f, 0.0, 1.5)
        path = root / "cam" / f"{f:02d}.png"
        write_png(path, np.full((height, width, 3), 0.5, np.float32))
        paths.append(path)
        sweep = cast(poses[f])
        ok = sweep.returned
        local = sweep.points_sensor()
        points.append((local @ poses[f][:3, :3].T + poses[f][:3, 3]).astype(np.float32))
        intensity.append(sweep.intensity[ok].astype(np.float32))
        stamps.append(np.full(int(ok.sum()), times[f]))
        beams.append(sweep.beam[ok].astype(np.int16))
    cams = [CameraSequence("cam", width, height, K, c2w, paths, times)]
    lidar = LidarSweeps(points, poses[:, :3, 3].copy(), intensity, stamps, beams, poses, BEAMS)
    train, test = holdout_split(frames, holdout)
    return SceneData("lidar-test", cams, times, np.arange(frames), train, test, lidar, []).validate()
