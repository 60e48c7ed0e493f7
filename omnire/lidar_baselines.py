"""Two LiDAR "renderers" that need no training, scored beside every rendered sweep
(docs/lidar.md, "Baselines"); each answers the rays of a held-out sweep with a
:class:`~omnire.lidar_metrics.RenderedSweep` (a ray either returns, drop probability 0, or
does not, drop probability 1).

- :func:`nearest_sweep_render`: the nearest training sweep moved by the ego motion. Its
  world returns are seen from the held-out sensor as it moves during its sweep; each
  held-out ray takes the nearest of the returns within ``max_angle_deg`` of its direction;
  a ray with none returns nothing.
- :func:`lidar_mesh` and :func:`mesh_render`: the LiDARsim-style mesh. Each training sweep's
  range image is triangulated between neighbouring cells (two triangles per 2 x 2 block of
  returns, beams in elevation order, azimuth wrapping), dropping triangles seen edge-on or
  with an edge long against their range (they bridge depth discontinuities); all sweeps'
  triangles, in the world frame, are ray-cast at the held-out rays
  (:func:`omnire.raycast.first_hits`). The intensity of a hit is that of the nearest
  training return; a ray that hits nothing (or outside the range limits) returns nothing.
"""
from __future__ import annotations

import dataclasses
from typing import Iterable, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

from omnire.beams import spherical
from omnire.data.scene import BeamModel, SceneData, SceneDataError
from omnire.interpolation import interpolate_poses
from omnire.lidar_metrics import RenderedSweep, boxes_at, lidar_metrics, mean_metrics
from omnire.lidarsweep import SweepRays, recorded_sweep, sensor_path
from omnire.raycast import first_hits


def cell_tolerance_deg(model: BeamModel) -> float:
    """Half the diagonal of the finest cell of ``model``'s grid (azimuth step by the
    smallest gap between beam elevations), degrees: how far from a ray's direction a
    return still belongs to that ray."""
    gaps = np.diff(np.sort(model.elevations_deg))
    finest = float(gaps.min()) if len(gaps) else model.azimuth_resolution_deg
    return 0.5 * float(np.hypot(model.azimuth_resolution_deg, finest))


def _nearest_per_ray(ray: np.ndarray, rng: np.ndarray, R: int) -> np.ndarray:
    """For candidate returns on rays ``ray`` (M,) at ranges ``rng`` (M,), the candidate index
    of the nearest one of each of R rays (-1 where none): (R,)."""
    best = np.full(R, -1, dtype=np.int64)
    if len(ray):
        order = np.lexsort((rng, ray))
        first = np.ones(len(order), dtype=bool)
        first[1:] = ray[order][1:] != ray[order][:-1]
        best[ray[order][first]] = order[first]
    return best


def nearest_sweep_render(points: np.ndarray, intensity: Optional[np.ndarray], target: SweepRays,
                         pose_times: np.ndarray, sensor_to_world: np.ndarray, max_angle_deg: float,
                         time_bins: int = 200) -> RenderedSweep:
    """The returns ``points`` (N, 3) (world; ``intensity`` (N,) or None) of another sweep
    seen from the held-out sweep's sensor and put on its rays ``target``: each ray takes
    the nearest (in range) of the returns within ``max_angle_deg`` of its direction.

    Args:
        pose_times, sensor_to_world: the held-out sensor's track ((K,) seconds, (K, 4, 4)).
        max_angle_deg: the angular tolerance (:func:`cell_tolerance_deg` for a beam grid).
        time_bins: the rays are taken in this many groups by firing time, each seen from
            the sensor's pose in the middle of its group (a 0.1 s sweep in 200 groups: 0.5
            ms, 5 mm at 36 km/h), so the sensor's motion during the sweep is followed.
    """
    points = np.asarray(points, dtype=np.float64)
    R = len(target)
    if points.ndim != 2 or points.shape[1] != 3:
        raise SceneDataError(f"nearest_sweep_render: points {points.shape}, expected (N, 3)")
    if R == 0:
        return RenderedSweep(np.zeros(0), np.zeros(0), np.zeros(0))
    chord = 2.0 * np.sin(np.deg2rad(max_angle_deg) / 2.0)
    edges = np.linspace(target.times.min(), target.times.max(), time_bins + 1)
    group = np.clip(np.searchsorted(edges, target.times, side="right") - 1, 0, time_bins - 1)
    pose = interpolate_poses(pose_times, sensor_to_world, (edges[:-1] + edges[1:]) / 2.0)  # (time_bins, 4, 4)
    margin = 2.0 * max_angle_deg + 0.5  # degrees of azimuth around a group's rays worth testing
    pair_ray, pair_point = [], []
    for g in np.unique(group):
        rays = np.flatnonzero(group == g)
        rot, origin = pose[g, :3, :3], pose[g, :3, 3]
        local = (points - origin) @ rot  # (N, 3) in the sensor frame at the group's time
        unit = local / np.linalg.norm(local, axis=1, keepdims=True).clip(1e-12)
        ray_dir = target.directions[rays] @ rot
        _, ray_az, _ = spherical(ray_dir)
        centre = np.rad2deg(np.arctan2(np.sin(np.deg2rad(ray_az)).mean(), np.cos(np.deg2rad(ray_az)).mean()))
        half = np.abs((ray_az - centre + 180.0) % 360.0 - 180.0).max()
        _, az, _ = spherical(unit)
        near = np.flatnonzero(np.abs((az - centre + 180.0) % 360.0 - 180.0) <= half + margin)
        if not len(near):
            continue
        pairs = cKDTree(ray_dir).sparse_distance_matrix(cKDTree(unit[near]), chord, output_type="ndarray")
        pair_ray.append(rays[pairs["i"]])
        pair_point.append(near[pairs["j"]])
    ray = np.concatenate(pair_ray) if pair_ray else np.zeros(0, np.int64)
    point = np.concatenate(pair_point) if pair_point else np.zeros(0, np.int64)
    rng = np.linalg.norm(points[point] - target.origins[ray], axis=1)
    best = _nearest_per_ray(ray, rng, R)
    out_range = np.full(R, np.nan)
    out_value = np.full(R, np.nan)
    hit = best >= 0
    out_range[hit] = rng[best[hit]]
    if intensity is not None:
        out_value[hit] = np.asarray(intensity, dtype=np.float64)[point[best[hit]]]
    return RenderedSweep(out_range, out_value, np.where(hit, 0.0, 1.0))


@dataclasses.dataclass
class LidarMesh:
    """Accumulated training sweeps as one world-frame triangle mesh.

    Attributes:
        verts: (V, 3) float64 world returns; faces: (Fc, 3) int64 vertex indices.
        intensity: (V,) float64 recorded intensity of each vertex (NaN where unknown).
        tree: k-d tree of ``verts`` (the intensity of a hit is its nearest vertex's).
        min_range, max_range: the sensor's range limits (metres).
    """

    verts: np.ndarray
    faces: np.ndarray
    intensity: np.ndarray
    tree: cKDTree
    min_range: float
    max_range: float


def sweep_triangles(rays: SweepRays, model: BeamModel, max_incidence_deg: float = 89.0,
                    max_edge_ratio: float = 1.0) -> np.ndarray:
    """(T, 3) triangles over the rays (indices into ``rays``) of one sweep on its beam grid.

    Two triangles per 2 x 2 block of neighbouring cells (beams adjacent in elevation,
    columns adjacent in azimuth, wrapping at 360 degrees) whose three corners returned;
    kept when the angle between the triangle's normal and the ray to its centre is at most
    ``max_incidence_deg`` and its longest edge at most ``max_edge_ratio`` times the range of
    its nearest corner.
    """
    if not rays.drops_known:
        raise SceneDataError("sweep_triangles: the sweep's rays are not a beam grid (no beam model)")
    B, A = model.num_beams, model.num_azimuths
    if len(rays) != B * A:
        raise SceneDataError(f"sweep_triangles: {len(rays)} rays, expected {B} x {A} (the beam model's grid)")
    grid = (rays.beam.astype(np.int64) * A + rays.column).argsort()  # ray index of cell (beam, column); int16 beams overflow
    rows = model.order()  # beams top to bottom
    top, bottom = rows[:-1], rows[1:]
    col = np.arange(A)
    nxt = (col + 1) % A
    c00 = grid[top[:, None] * A + col[None]].reshape(-1)
    c01 = grid[top[:, None] * A + nxt[None]].reshape(-1)
    c10 = grid[bottom[:, None] * A + col[None]].reshape(-1)
    c11 = grid[bottom[:, None] * A + nxt[None]].reshape(-1)
    tri = np.concatenate([np.stack([c00, c10, c01], 1), np.stack([c01, c10, c11], 1)])
    tri = tri[rays.returned[tri].all(axis=1)]
    p = rays.origins + rays.directions * np.nan_to_num(rays.range)[:, None]
    v = p[tri]  # (T, 3, 3)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)
    view = v.mean(axis=1) - rays.origins[tri].mean(axis=1)
    view /= np.linalg.norm(view, axis=1, keepdims=True).clip(1e-12)
    facing = np.abs((n * view).sum(1)) >= np.cos(np.deg2rad(max_incidence_deg))
    edge = np.stack([np.linalg.norm(v[:, i] - v[:, (i + 1) % 3], axis=1) for i in range(3)], 1).max(axis=1)
    short = edge <= max_edge_ratio * rays.range[tri].min(axis=1)
    return tri[facing & short]


def lidar_mesh(sweeps: Iterable[SweepRays], model: BeamModel, max_incidence_deg: float = 89.0,
               max_edge_ratio: float = 1.0) -> LidarMesh:
    """The training sweeps (each on ``model``'s grid) triangulated (:func:`sweep_triangles`)
    and joined in the world frame."""
    verts, faces, values, base = [], [], [], 0
    for rays in sweeps:
        tri = sweep_triangles(rays, model, max_incidence_deg, max_edge_ratio)
        used, inverse = np.unique(tri.reshape(-1), return_inverse=True)
        verts.append(rays.origins[used] + rays.directions[used] * rays.range[used, None])
        values.append(rays.intensity[used].astype(np.float64))
        faces.append(inverse.reshape(-1, 3) + base)
        base += len(used)
    if not verts:
        raise SceneDataError("lidar_mesh: no training sweep")
    all_verts = np.concatenate(verts)
    return LidarMesh(all_verts, np.concatenate(faces).astype(np.int64), np.concatenate(values), cKDTree(all_verts),
                     model.min_range, model.max_range)


def mesh_render(mesh: LidarMesh, target: SweepRays) -> RenderedSweep:
    """The held-out rays ``target`` cast at ``mesh``: range of the first hit within the
    range limits, intensity of the mesh vertex nearest the hit, else no return."""
    hits = first_hits(mesh.verts, mesh.faces, target.origins, target.directions)
    d = hits.distance
    hit = np.isfinite(d) & (d >= mesh.min_range) & (d <= mesh.max_range)
    out_range = np.where(hit, d, np.nan)
    out_value = np.full(len(target), np.nan)
    if hit.any():
        at = target.origins[hit] + target.directions[hit] * d[hit, None]
        out_value[hit] = mesh.intensity[mesh.tree.query(at)[1]]
    return RenderedSweep(out_range, out_value, np.where(hit, 0.0, 1.0))


def sensor_returns(scene: SceneData, frame: int) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """World returns (N, 3) of ``frame``'s sweep and their intensity (N,) (or None): those
    of the sensor of the beam model when beams are recorded (another sensor's are left out)."""
    lidar = scene.lidar
    points = np.asarray(lidar.points[frame], dtype=np.float64)
    value = None if lidar.intensity is None else lidar.intensity[frame]
    if lidar.beams is not None:
        mine = lidar.beams[frame] >= 0
        points, value = points[mine], None if value is None else value[mine]
    return points, value


def baseline_metrics(scene: SceneData, test_frames: Sequence[int], train_frames: Sequence[int],
                     max_angle_deg: Optional[float] = None, mesh_sweeps: int = 4) -> dict[str, dict]:
    """The mean :func:`~omnire.lidar_metrics.lidar_metrics` of each baseline over the
    held-out sweeps of ``test_frames`` (frames without LiDAR are skipped), with the boxes of
    the scene at each frame: ``{"nearest_sweep": ..., "mesh": ...}`` (the mesh needs a beam
    model). ``max_angle_deg``: the nearest-sweep tolerance, by default
    :func:`cell_tolerance_deg` of the beam model (required without one). ``mesh_sweeps``:
    the mesh of a held-out sweep joins the training sweeps nearest to it in frame index
    (docs/lidar.md says why not all of them); 0 joins every training sweep.
    """
    lidar = scene.lidar
    if lidar is None:
        raise SceneDataError(f"scene {scene.name}: no LiDAR to evaluate")
    model = lidar.beam_model
    if max_angle_deg is None:
        if model is None:
            raise SceneDataError("baseline_metrics: no beam model; give max_angle_deg")
        max_angle_deg = cell_tolerance_deg(model)
    have = set(lidar.available_frames())
    train = np.array([f for f in train_frames if f in have], dtype=np.int64)
    tests = [f for f in test_frames if f in have]
    if not len(train) or not tests:
        raise SceneDataError(f"scene {scene.name}: no training or held-out frame with LiDAR")
    path = sensor_path(scene)
    rays: dict[int, SweepRays] = {}

    def rays_of(f: int) -> SweepRays:
        if f not in rays:
            rays[f] = recorded_sweep(scene, f, grid_only=True)
        return rays[f]

    scores: dict[str, list[dict]] = {"nearest_sweep": [], "mesh": []}
    for f in tests:
        target = recorded_sweep(scene, f, grid_only=True)
        boxes = boxes_at(scene, f)
        by_distance = train[np.argsort(np.abs(train - f), kind="stable")]  # ties: the earlier frame
        points, value = sensor_returns(scene, int(by_distance[0]))
        rendered = nearest_sweep_render(points, value, target, path.times, path.poses, max_angle_deg)
        scores["nearest_sweep"].append(lidar_metrics(rendered, target, boxes))
        if model is not None:
            chosen = by_distance[:mesh_sweeps] if mesh_sweeps > 0 else by_distance
            mesh = lidar_mesh((rays_of(int(g)) for g in chosen), model)
            scores["mesh"].append(lidar_metrics(mesh_render(mesh, target), target, boxes))
    return {name: mean_metrics(values) for name, values in scores.items() if values}
