"""Generate a synthetic driving scene in the processed-scene format, with ground truth.

Output (docs/conventions.md, "The processed scene format"; ``style`` picks the dataset conventions):

- ``images/{t:03d}_{cam}.jpg``, ``sky_masks/``, ``dynamic_masks/{all,human,vehicle}/`` (coarse:
  projected 3D boxes), ``fine_dynamic_masks/...`` (exact visible actor pixels),
- ``extrinsics/``, ``intrinsics/``, ``ego_pose/`` (``lidar_pose/`` for nuScenes), ``lidar/``,
- ``instances/instances_info.json``, ``instances/frame_instances.json``, ``humanpose/smpl.pkl``,
- ``depth/{t:03d}_{cam}.npy``: rendered z-depth (float32, inf = sky), not part of the format,
- ``ground_truth.npz`` + ``ground_truth.json``: true boxes and body poses (generator world),
  what was written (after noise), the noise settings and the generator-to-file transform.

Intrinsics and boxes are written in the conventions the reference's files have for the
style's dataset (``omnire_processed.formats``): the pixel-centre convention of
``PIXEL_CENTRES`` (``cx_file = cx - 0.5`` for "integer" datasets; the three styles are all
"half", i.e. omnire's, so ``cx_file = cx``) and the box axes of ``BOX_HEADING_AXIS`` (PandaSet
style: local +y along the heading and box_size = (width, length, height); others: x along the
heading, (length, width, height)) and the LiDAR intensity scale of its ``LIDAR_LAYOUTS``
entry (PandaSet and nuScenes 0-255, Waymo's unbounded raw scale: the ray-traced intensity in
[0, 1] through ``IntensityScale.from_unit``, so the processed reader reads it back). The
ground truth is in omnire's conventions.
"""
from __future__ import annotations

import dataclasses
import json
import pickle
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from omnire.api import rigid
from omnire_processed.boxes import AXES, axis_fix, size_fix
from omnire_processed.formats import BOX_HEADING_AXIS, LIDAR_LAYOUTS, PIXEL_CENTRES, WAYMO_TO_OPENCV
from omnire_synthetic import images
from omnire.api import BeamModel
from omnire_synthetic.meshes import Mesh, rot_z
from omnire_synthetic.lidar import LidarSpec, cast_sweep
from omnire_synthetic.render import rasterize, sample_texture, sphere_in_frustum
from omnire_synthetic.textures import MAT, build_textures, sky_color
from omnire_synthetic.world import (
    LIDAR_HEIGHT,
    PRESETS,
    Actor,
    box_mesh_world,
    build_actors,
    build_static,
    camera_rigs,
    ego_trajectory,
)

Style = Literal["pandaset", "waymo", "nuscenes"]

CLASS_NAMES = {
    "pandaset": {"car": "Car", "pedestrian": "Pedestrian", "cyclist": "Bicycle"},
    "waymo": {"car": "Vehicle", "pedestrian": "Pedestrian", "cyclist": "Cyclist"},
    "nuscenes": {"car": "vehicle.car", "pedestrian": "human.pedestrian.adult", "cyclist": "vehicle.bicycle"},
}
CATEGORY = {"car": "vehicle", "pedestrian": "human", "cyclist": "cyclist"}
WAYMO_FLOW_CLASS = {"car": 1, "pedestrian": 2, "cyclist": 4}
GROUND_MATERIALS = (MAT["asphalt"], MAT["marking"], MAT["marking_yellow"], MAT["paving"], MAT["grass"])
SUN = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])
# nuScenes LiDAR axes: x right, y forward, z up (ego: x forward, y left).
NUSCENES_LIDAR_TO_EGO = rigid(rot_z(-np.pi / 2))


@dataclasses.dataclass
class SynthOptions:
    """Generator settings (the ``omnire synth`` flags)."""

    seed: int = 0
    """Random seed; the same seed and options give the same scene."""
    frames: int = 50
    """Number of frames."""
    width: int = 360
    """Image width in pixels."""
    height: int = 240
    """Image height in pixels."""
    num_cameras: int = 3
    """Cameras (1-6): front, front-left, front-right, left, right, back."""
    style: Style = "pandaset"
    """Conventions to write: pandaset (per-frame extrinsics, 5-column LiDAR), waymo (per-camera extrinsics in Waymo camera axes, 14-column LiDAR), nuscenes (per-frame extrinsics, lidar_pose/, 4-column LiDAR)."""
    y_down_world: bool = False
    """Write world-frame data relative to the first front camera (a y-down world, as the reference leaves nuScenes)."""
    fps: float = 10.0
    """Frame rate in Hz."""
    box_noise_translation: float = 0.0
    """Std-dev (m) of noise added to the written box centres (x, y; a third of it on z)."""
    box_noise_yaw_deg: float = 0.0
    """Std-dev (degrees) of noise added to the written box headings."""
    pose_noise_deg: float = 0.0
    """Std-dev (degrees, per axis) of noise on every written body-joint rotation and global orientation."""
    drop_pose_frames: float = 0.0
    """Fraction of pedestrian pose frames marked invalid (dropped) in smpl.pkl."""
    lidar_beams: int = 32
    """LiDAR beams, evenly spread over the elevation range."""
    lidar_elevation_deg: tuple[float, float] = (-25.0, 10.0)
    """LiDAR beam elevation range (degrees)."""
    lidar_elevations_deg: tuple[float, ...] = ()
    """LiDAR beam elevations (degrees), one per beam, in place of --lidar-beams evenly spread over --lidar-elevation-deg (an uneven layout such as a real sensor's)."""
    lidar_azimuth_step_deg: float = 0.4
    """LiDAR azimuth resolution (degrees)."""
    lidar_max_range: float = 120.0
    """LiDAR max range (m): farther surfaces return nothing."""
    lidar_min_range: float = 0.3
    """LiDAR min range (m): nearer surfaces return nothing."""
    lidar_grazing_drop_deg: float = 85.0
    """LiDAR rays meeting a surface further than this from its normal (degrees) return nothing."""
    presence_radius: float = 80.0
    """Actors are annotated in frames where they are within this distance (m) of the ego."""
    write_depth: bool = True
    """Write rendered depth maps (depth/*.npy)."""
    jpeg_quality: int = 95
    """JPEG quality of the images."""
    threads: int = 1
    """Torch threads while generating (0 keeps the current setting); 1 is robust on contended cores."""


@dataclasses.dataclass
class FrameMesh:
    mesh: Mesh
    obj: np.ndarray  # (F_faces,) 0 = static, k = actor index + 1


def _frame_mesh(static: Mesh, actors: list[Actor], t: int, template) -> FrameMesh:
    parts, objs = [static], [np.zeros(static.faces.shape[0], np.int64)]
    for k, a in enumerate(actors):
        m = a.mesh_at(t, template)
        parts.append(m)
        objs.append(np.full(m.faces.shape[0], k + 1, np.int64))
    return FrameMesh(Mesh.concat(parts), np.concatenate(objs))


def _object_spheres(actors: list[Actor], t: int, world_to_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Actor bounding spheres at frame t: centres (N, 3) in the given frame, radii (N,)."""
    centres = np.stack([a.poses[t, :3, 3] for a in actors]) @ world_to_frame[:3, :3].T + world_to_frame[:3, 3]
    radii = np.array([np.linalg.norm(a.size) / 2 + 0.3 for a in actors])
    return centres, radii


def _visible_faces(actors: list[Actor], t: int, c2w: np.ndarray, K: np.ndarray, W: int, H: int,
                   n_static: int, ranges: np.ndarray) -> torch.Tensor | None:
    """Face indices of the static mesh plus the actors whose bounding sphere meets the view
    frustum (None = all faces). Saves rasterising bodies behind or beside the camera."""
    if not actors:
        return None
    centres, radii = _object_spheres(actors, t, np.linalg.inv(c2w))
    visible = sphere_in_frustum(centres, radii, K, W, H)
    if visible.all():
        return None
    parts = [torch.arange(0, n_static)]
    parts += [torch.arange(int(ranges[k + 1]), int(ranges[k + 2])) for k in np.flatnonzero(visible)]
    return torch.cat(parts)


def _to_frame(verts: np.ndarray, frame_to_world: np.ndarray) -> torch.Tensor:
    """World vertices (V, 3) float64 -> float32 tensor in the given frame (world->frame = inverse)."""
    R, t = frame_to_world[:3, :3], frame_to_world[:3, 3]
    return torch.from_numpy(((verts - t) @ R).astype(np.float32))


def _shade(face: torch.Tensor, bary: torch.Tensor, cam_pos: np.ndarray,
           textures: torch.Tensor, uv: torch.Tensor, mat: torch.Tensor, faces_t: torch.Tensor,
           verts_w: torch.Tensor) -> torch.Tensor:
    """Colours (P, 3) of hit pixels: texture times Lambert shading (two-sided)."""
    f = faces_t[face]  # (P, 3)
    uvp = (uv[f] * bary[..., None]).sum(1)
    col = sample_texture(textures, mat[face], uvp)
    tri = verts_w[f]  # (P, 3, 3)
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = n / n.norm(dim=1, keepdim=True).clamp(min=1e-12)
    p = (tri * bary[..., None]).sum(1)
    to_cam = torch.from_numpy(cam_pos.astype(np.float32)) - p
    n = torch.where(((n * to_cam).sum(1, keepdim=True) < 0), -n, n)
    sun = torch.from_numpy(SUN.astype(np.float32))
    shade = 0.5 + 0.45 * (n @ sun).clamp(min=0) + 0.05 * n[:, 2].clamp(min=0)
    return col * shade[:, None]


def generate(out: str | Path, preset: str = "urban", opts: SynthOptions | None = None, progress=None) -> dict:
    """Render and write one scene of ``preset`` (urban, highway, crowd, empty); returns a
    summary with timings."""
    opts = opts or SynthOptions()
    t_start = time.perf_counter()
    threads_before = torch.get_num_threads()
    if opts.threads > 0:
        torch.set_num_threads(opts.threads)
    try:
        return _generate(out, preset, opts, progress, t_start)
    finally:
        torch.set_num_threads(threads_before)


def _generate(out: str | Path, preset: str, opts: SynthOptions, progress, t_start: float) -> dict:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    if not 1 <= opts.num_cameras <= 6:
        raise ValueError("num_cameras must be between 1 and 6")
    if opts.frames < 1:
        raise ValueError("frames must be >= 1")
    out = Path(out)
    _prepare_output(out)
    spec = PRESETS[preset]
    rng = np.random.default_rng(opts.seed)
    F, W, H, C = opts.frames, opts.width, opts.height, opts.num_cameras
    times = np.arange(F) / opts.fps
    ego = ego_trajectory(spec, times)  # (F, 4, 4) generator world
    needs_body = spec.walkers + spec.crossers > 0
    template = None
    if needs_body:
        from omnire_body import load_template

        template = load_template()
    x_end = float(ego[-1, 0, 3])
    static = build_static(spec, rng, -40.0, x_end + 120.0)
    actors = build_actors(spec, rng, times, ego, template, opts.presence_radius)
    tex_np, refl_np = build_textures(opts.seed)
    textures = torch.from_numpy(tex_np)
    names, cam_to_ego, Ks = camera_rigs(C, W, H)
    lidar_to_ego = rigid(None, (0.0, 0.0, LIDAR_HEIGHT))

    # Generator world -> file world: an arbitrary log origin (exercises the reader's alignment).
    G = rigid(rot_z(rng.uniform(-np.pi, np.pi)), (*rng.uniform(-400.0, 400.0, 2), rng.uniform(-5.0, 30.0)))
    if opts.y_down_world:
        G = np.linalg.inv(G @ ego[0] @ cam_to_ego[0]) @ G
    t_setup = time.perf_counter() - t_start

    for d in ("images", "sky_masks", "extrinsics", "intrinsics", "lidar", "instances", "humanpose"):
        (out / d).mkdir(exist_ok=True)
    for kind in ("dynamic_masks", "fine_dynamic_masks"):
        for sub in ("all", "human", "vehicle"):
            (out / kind / sub).mkdir(parents=True, exist_ok=True)
    if opts.write_depth:
        (out / "depth").mkdir(exist_ok=True)
    pose_dir = out / ("lidar_pose" if opts.style == "nuscenes" else "ego_pose")
    pose_dir.mkdir(exist_ok=True)

    actor_cat = np.array(["static"] + [CATEGORY[a.kind] for a in actors])
    lidar_spec = LidarSpec(
        BeamModel(np.array(opts.lidar_elevations_deg, dtype=np.float64) if opts.lidar_elevations_deg
                  else np.linspace(*opts.lidar_elevation_deg, opts.lidar_beams), opts.lidar_azimuth_step_deg,
                  opts.lidar_max_range, opts.lidar_min_range, "synthetic"),
        refl_np, opts.lidar_grazing_drop_deg)
    lidar_counts = []
    t_render = t_lidar = t_write = 0.0

    for t in range(F):
        fm = _frame_mesh(static, actors, t, template)
        verts_w = torch.from_numpy(fm.mesh.verts.astype(np.float32))
        faces_t = torch.from_numpy(fm.mesh.faces)
        uv = torch.from_numpy(fm.mesh.uv.astype(np.float32))
        mat = torch.from_numpy(fm.mesh.mat)
        obj = torch.from_numpy(fm.obj)
        counts = np.bincount(fm.obj, minlength=len(actors) + 1)
        obj_ranges = np.concatenate([[0], np.cumsum(counts)])  # faces of object k: [r[k], r[k+1])
        present = [k for k, a in enumerate(actors) if a.present[t]]
        boxes = [box_mesh_world(actors[k], t) for k in present]
        box_mesh = Mesh.concat(boxes) if boxes else None
        box_owner = np.concatenate([np.full(b.faces.shape[0], k + 1) for k, b in zip(present, boxes)]) if boxes else None
        for c in range(C):
            t0 = time.perf_counter()
            c2w = ego[t] @ cam_to_ego[c]
            subset = _visible_faces(actors, t, c2w, Ks[c], W, H, static.faces.shape[0], obj_ranges)
            r = rasterize(_to_frame(fm.mesh.verts, c2w), faces_t, Ks[c], H, W, face_subset=subset)
            face = r.face.reshape(-1)
            hit = face >= 0
            img = np.empty((H * W, 3), np.float32)
            # Sky: gradient by the world elevation of each pixel ray.
            js, is_ = np.divmod(np.arange(H * W), W)
            d_cam = np.stack([(is_ + 0.5 - Ks[c][0, 2]) / Ks[c][0, 0], (js + 0.5 - Ks[c][1, 2]) / Ks[c][1, 1],
                              np.ones(H * W)], 1)
            d_w = d_cam @ c2w[:3, :3].T
            elev = d_w[:, 2] / np.linalg.norm(d_w, axis=1)
            img[:] = sky_color(elev)
            hit_np = hit.numpy()
            if hit_np.any():
                col = _shade(face[hit], r.bary.reshape(-1, 3)[hit], c2w[:3, 3], textures, uv, mat, faces_t, verts_w)
                img[hit_np] = col.numpy()
            obj_px = np.where(hit_np, obj[face.clamp(min=0)].numpy(), 0)
            cat_px = actor_cat[obj_px]
            fine = {"human": cat_px == "human", "vehicle": cat_px == "vehicle", "all": obj_px > 0}
            coarse = {k: np.zeros(H * W, bool) for k in fine}
            if box_mesh is not None:
                rb = rasterize(_to_frame(box_mesh.verts, c2w), torch.from_numpy(box_mesh.faces), Ks[c], H, W)
                bf = rb.face.reshape(-1).numpy()
                owner = np.where(bf >= 0, box_owner[np.clip(bf, 0, None)], 0)
                bcat = actor_cat[owner]
                coarse = {"human": bcat == "human", "vehicle": bcat == "vehicle", "all": owner > 0}
            t1 = time.perf_counter()
            t_render += t1 - t0
            stem = f"{t:03d}_{c}"
            images.write_rgb(out / "images" / f"{stem}.jpg", img.reshape(H, W, 3), opts.jpeg_quality)
            images.write_mask(out / "sky_masks" / f"{stem}.png", (~hit_np).reshape(H, W))
            for k in fine:
                images.write_mask(out / "fine_dynamic_masks" / k / f"{stem}.png", fine[k].reshape(H, W))
                images.write_mask(out / "dynamic_masks" / k / f"{stem}.png", coarse[k].reshape(H, W))
            if opts.write_depth:
                np.save(out / "depth" / f"{stem}.npy", r.depth.numpy().astype(np.float32))
            t_write += time.perf_counter() - t1

        # LiDAR: first hits of every beam x azimuth ray, ray-traced (omnire_synthetic.lidar).
        t0 = time.perf_counter()
        sensor = ego[t] @ lidar_to_ego
        sweep = cast_sweep(fm.mesh.verts, fm.mesh.faces, fm.mesh.mat, sensor, lidar_spec)
        ok = sweep.returned
        p_s = sweep.points_sensor()  # (N, 3) sensor frame
        fl = torch.from_numpy(sweep.face[ok])
        intensity = sweep.intensity[ok].astype(np.float64)  # (N,) in [0, 1]
        lidar_counts.append(int(ok.sum()))
        t_lidar += time.perf_counter() - t0
        t1 = time.perf_counter()
        p_world = p_s @ sensor[:3, :3].T + sensor[:3, 3]
        _write_lidar(out, t, opts.style, p_world, intensity, sweep.beam[ok], ego[t], sensor, obj[fl].numpy(),
                     mat[fl].numpy(), actors, times)
        # Poses of this frame.
        if opts.style == "nuscenes":
            _write_matrix(pose_dir / f"{t:03d}.txt", G @ sensor @ NUSCENES_LIDAR_TO_EGO)
        elif opts.style == "pandaset":
            _write_matrix(pose_dir / f"{t:03d}.txt", G @ sensor)  # PandaSet's ego pose is the LiDAR pose
        else:
            _write_matrix(pose_dir / f"{t:03d}.txt", G @ ego[t])
        if opts.style in ("pandaset", "nuscenes"):
            for c in range(C):
                _write_matrix(out / "extrinsics" / f"{t:03d}_{c}.txt", G @ ego[t] @ cam_to_ego[c])
        t_write += time.perf_counter() - t1
        if progress is not None:
            progress(t + 1, F)

    t1 = time.perf_counter()
    for c in range(C):
        if opts.style == "waymo":
            _write_matrix(out / "extrinsics" / f"{c}.txt", cam_to_ego[c] @ np.linalg.inv(WAYMO_TO_OPENCV))
        K = Ks[c]
        # The style's dataset's pixel-centre convention (Ks centre pixels at +0.5).
        shift = 0.5 if PIXEL_CENTRES[opts.style] == "integer" else 0.0
        vals = [K[0, 0], K[1, 1], K[0, 2] - shift, K[1, 2] - shift, 0.0, 0.0, 0.0, 0.0, 0.0]
        (out / "intrinsics" / f"{c}.txt").write_text("\n".join(f"{v:.10f}" for v in vals) + "\n")
    gt = _write_annotations(out, preset, opts, rng, actors, ego, cam_to_ego, Ks, G, times, names)
    t_write += time.perf_counter() - t1
    total = time.perf_counter() - t_start
    summary = {
        "out": str(out), "preset": preset, "style": opts.style, "frames": F, "cameras": C,
        "size": [W, H], "actors": len(actors), "pedestrians": len(gt["pedestrians"]),
        "lidar_points_mean": float(np.mean(lidar_counts)),
        "seconds": {"total": round(total, 2), "setup": round(t_setup, 2), "render": round(t_render, 2),
                    "lidar": round(t_lidar, 2), "write": round(t_write, 2)},
    }
    meta = json.loads((out / "ground_truth.json").read_text())
    meta["generation"] = summary
    (out / "ground_truth.json").write_text(json.dumps(meta, indent=1))
    return summary


_OUTPUT_DIRS = ("images", "sky_masks", "dynamic_masks", "fine_dynamic_masks", "extrinsics", "intrinsics", "ego_pose",
                "lidar_pose", "lidar", "instances", "humanpose", "depth")


def _prepare_output(out: Path) -> None:
    """Create ``out``; clear a previous synthetic scene there (stale files of another style
    would confuse readers); refuse to write into any other non-empty folder."""
    import shutil

    if out.exists() and any(out.iterdir()):
        if not (out / "ground_truth.json").is_file():
            raise FileExistsError(f"{out}: not empty and not a synthetic scene; choose an empty or new folder")
        for d in _OUTPUT_DIRS:
            if (out / d).is_dir():
                shutil.rmtree(out / d)
    out.mkdir(parents=True, exist_ok=True)


def _write_matrix(path: Path, M: np.ndarray) -> None:
    np.savetxt(path, M, fmt="%.12f")


def _write_lidar(out: Path, t: int, style: str, p_world: np.ndarray, intensity: np.ndarray, beams: np.ndarray,
                 ego_t: np.ndarray, sensor: np.ndarray, obj: np.ndarray, mat: np.ndarray,
                 actors: list[Actor], times: np.ndarray) -> None:
    """One LiDAR file in the style's column layout (rows float32), ``intensity`` (N,) in
    [0, 1] on the style's dataset's scale (``LidarLayout.intensity_scale``)."""
    N = len(p_world)
    intensity = LIDAR_LAYOUTS[style].intensity_scale.from_unit(intensity)
    if style == "waymo":
        w2e = np.linalg.inv(ego_t)
        p_e = p_world @ w2e[:3, :3].T + w2e[:3, 3]
        origin = np.broadcast_to((w2e @ sensor)[:3, 3], (N, 3))
        flow = np.zeros((N, 3))
        flow_cls = np.zeros(N)
        F = len(times)
        for k, a in enumerate(actors):
            sel = obj == k + 1
            if not sel.any():
                continue
            flow_cls[sel] = WAYMO_FLOW_CLASS[a.kind]
            t2 = min(t + 1, F - 1)
            t1 = t2 - 1 if t2 > 0 else t2
            if t2 == t1:
                continue
            # Scene flow: velocity (m/s) of the actor's material point, in the ego frame.
            M = a.poses[t2] @ np.linalg.inv(a.poses[t1])
            moved = p_world[sel] @ M[:3, :3].T + M[:3, 3]
            flow[sel] = ((moved - p_world[sel]) / (times[t2] - times[t1])) @ w2e[:3, :3].T
        ground = np.isin(mat, GROUND_MATERIALS).astype(np.float64)
        rows = np.column_stack([origin, p_e, flow, flow_cls, ground, intensity, np.zeros(N), np.zeros(N)])
    elif style == "pandaset":
        s2w = np.linalg.inv(sensor)
        p_l = p_world @ s2w[:3, :3].T + s2w[:3, 3]
        rows = np.column_stack([p_l, intensity, np.zeros(N)])
    else:  # nuscenes: LiDAR frame x right, y forward, z up
        L = sensor @ NUSCENES_LIDAR_TO_EGO
        w2l = np.linalg.inv(L)
        p_l = p_world @ w2l[:3, :3].T + w2l[:3, 3]
        rows = np.column_stack([p_l, intensity])
    rows.astype(np.float32).tofile(out / "lidar" / f"{t:03d}.bin")


def _rot_noise(rng: np.random.Generator, shape: tuple[int, ...], deg: float) -> np.ndarray:
    from omnire.api import axis_angle_to_rotmat

    if deg <= 0:
        return np.broadcast_to(np.eye(3), shape + (3, 3)).copy()
    return axis_angle_to_rotmat(rng.normal(scale=np.deg2rad(deg), size=shape + (3,)))


def _write_annotations(out: Path, preset: str, opts: SynthOptions, rng: np.random.Generator, actors: list[Actor],
                       ego: np.ndarray, cam_to_ego: np.ndarray, Ks: np.ndarray, G: np.ndarray,
                       times: np.ndarray, cam_names: list[str]) -> dict:
    F = len(times)
    names = CLASS_NAMES[opts.style]
    # Box axes as the reference writes them for this dataset (omnire's box x = heading).
    k_axis = AXES.index(BOX_HEADING_AXIS[opts.style])
    to_file = np.eye(4)
    to_file[:3, :3] = axis_fix(k_axis).T
    info, frame_instances = {}, {str(t): [] for t in range(F)}
    written_poses = []
    for i, a in enumerate(actors):
        noisy = a.poses.copy()
        if opts.box_noise_translation > 0 or opts.box_noise_yaw_deg > 0:
            dt = rng.normal(scale=opts.box_noise_translation, size=(F, 3)) * np.array([1.0, 1.0, 1.0 / 3.0])
            dyaw = rng.normal(scale=np.deg2rad(opts.box_noise_yaw_deg), size=F)
            for t in range(F):
                noisy[t, :3, :3] = rot_z(dyaw[t]) @ noisy[t, :3, :3]
                noisy[t, :3, 3] += dt[t]
        written_poses.append(noisy)
        frames = np.flatnonzero(a.present)
        info[str(i)] = {
            "id": a.track_id,
            "class_name": names[a.kind],
            "frame_annotations": {
                "frame_idx": [int(t) for t in frames],
                "obj_to_world": [(G @ noisy[t] @ to_file).tolist() for t in frames],
                "box_size": [[float(s) for s in size_fix(a.size, k_axis)] for _ in frames],
            },
        }
        for t in frames:
            frame_instances[str(t)].append(i)
    (out / "instances" / "instances_info.json").write_text(json.dumps(info))
    (out / "instances" / "frame_instances.json").write_text(json.dumps(frame_instances))

    smpl, peds = {}, []
    go_true, bp_true, go_written, bp_written, valid_written, transl = [], [], [], [], [], []
    c2w = np.einsum("fij,cjk->fcik", ego, cam_to_ego)  # (F, C, 4, 4)
    for i, a in enumerate(actors):
        if a.kind != "pedestrian":
            continue
        go = a.global_orient @ _rot_noise(rng, (F,), opts.pose_noise_deg)
        bp = a.body_pose @ _rot_noise(rng, (F, 23), opts.pose_noise_deg)
        sel_cam = np.zeros(F, np.int64)
        valid = a.present.copy()
        for t in range(F):
            centre = a.poses[t, :3, 3]
            best, best_score = -1, -np.inf
            for c in range(len(cam_to_ego)):
                w2c = np.linalg.inv(c2w[t, c])
                p = w2c[:3, :3] @ centre + w2c[:3, 3]
                if p[2] <= 0.5:
                    continue
                u, v = Ks[c][0, 0] * p[0] / p[2] + Ks[c][0, 2], Ks[c][1, 1] * p[1] / p[2] + Ks[c][1, 2]
                W, H = 2 * Ks[c][0, 2], 2 * Ks[c][1, 2]
                if not (0 <= u < W and 0 <= v < H):
                    continue
                score = -abs(u / W - 0.5)  # most central view
                if score > best_score:
                    best, best_score = c, score
            if best < 0:
                valid[t] = False
            else:
                sel_cam[t] = best
        if opts.drop_pose_frames > 0:
            valid &= rng.random(F) >= opts.drop_pose_frames
        # global_orient in the OpenCV frame of the selected camera (world-independent).
        R_c2w = c2w[np.arange(F), sel_cam, :3, :3]  # (F, 3, 3)
        go_cam = np.einsum("fji,fjk->fik", R_c2w, go)
        smpl[i] = {
            "smpl": {
                "global_orient": go_cam[:, None].astype(np.float32),
                "body_pose": bp.astype(np.float32),
                "betas": np.zeros((F, 10), np.float32),
            },
            "valid_mask": valid,
            "selected_cam_idx": sel_cam,
        }
        peds.append(a.track_id)
        go_true.append(a.global_orient)
        bp_true.append(a.body_pose)
        go_written.append(go)
        bp_written.append(bp)
        valid_written.append(valid)
        transl.append(a.transl)
    with open(out / "humanpose" / "smpl.pkl", "wb") as f:
        pickle.dump(smpl, f, protocol=4)

    N = len(actors)
    arrays = {
        "file_from_generator": G,
        "ego_to_world": ego,
        "cam_to_ego": cam_to_ego,
        "intrinsics": Ks,
        "timestamps": times,
        "camera_names": np.array(cam_names),
        "track_ids": np.array([a.track_id for a in actors], dtype=str) if N else np.zeros(0, str),
        "track_kinds": np.array([a.kind for a in actors], dtype=str) if N else np.zeros(0, str),
        "box_poses_true": np.stack([a.poses for a in actors]) if N else np.zeros((0, F, 4, 4)),
        "box_poses_written": np.stack(written_poses) if N else np.zeros((0, F, 4, 4)),
        "box_sizes": np.stack([a.size for a in actors]) if N else np.zeros((0, 3)),
        "present": np.stack([a.present for a in actors]) if N else np.zeros((0, F), bool),
        "stationary": np.array([a.stationary for a in actors], bool),
        "pedestrian_ids": np.array(peds, dtype=str) if peds else np.zeros(0, str),
        "global_orient_true": np.stack(go_true) if peds else np.zeros((0, F, 3, 3)),
        "body_pose_true": np.stack(bp_true) if peds else np.zeros((0, F, 23, 3, 3)),
        "global_orient_written": np.stack(go_written) if peds else np.zeros((0, F, 3, 3)),
        "body_pose_written": np.stack(bp_written) if peds else np.zeros((0, F, 23, 3, 3)),
        "pose_valid_written": np.stack(valid_written) if peds else np.zeros((0, F), bool),
        "smpl_transl": np.stack(transl) if peds else np.zeros((0, F, 3)),
    }
    np.savez_compressed(out / "ground_truth.npz", **arrays)
    meta = {
        "format": "omnire synthetic ground truth v1",
        "preset": preset, "seed": opts.seed, "style": opts.style, "frames": F, "fps": opts.fps,
        "y_down_world": opts.y_down_world,
        "noise": {"box_translation_m": opts.box_noise_translation, "box_yaw_deg": opts.box_noise_yaw_deg,
                  "pose_deg": opts.pose_noise_deg, "dropped_pose_fraction": opts.drop_pose_frames},
        "frames_note": "All poses in ground_truth.npz are in the generator world (z up, street along +x); "
                       "file_from_generator maps them to the world of the written files. Body vertices: "
                       "world = global_orient @ canonical_lbs(v) + box centre (SMPL transl in smpl_transl). "
                       "Pedestrian global_orient maps SMPL canonical (x left, y up, z forward) to the world.",
        "options": dataclasses.asdict(opts),
    }
    (out / "ground_truth.json").write_text(json.dumps(meta, indent=1))
    return {"pedestrians": peds}
