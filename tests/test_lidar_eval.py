"""The rays of a recorded sweep (omnire.lidarsweep), the metrics of a rendered sweep against
it (omnire.lidar_metrics, each against a brute-force computation), and the two baselines
(omnire.lidar_baselines) on scenes of planes whose sweeps have exact answers."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omnire.beams import spherical
from omnire.data.scene import ActorTrack, BeamModel, LidarSweeps, SceneData, SceneDataError
from omnire.geometry import axis_angle_to_rotmat, rigid, rot_z, slerp_rotmats
from omnire.interpolation import bracket, extend_poses, interpolate_poses, interpolate_rotations
from omnire.lidar_baselines import (baseline_metrics, cell_tolerance_deg, lidar_mesh, mesh_render,
                                    nearest_sweep_render, sweep_triangles)
from omnire.lidar_evaluation import rendered_sweep, score_sweep
from omnire.lidar_metrics import Box, RenderedSweep, boxes_at, lidar_metrics, mean_metrics
from omnire.lidarmodel import LidarRender
from omnire.lidarsweep import SensorPath, recorded_sweep, sectors_of, sweep_rays
from omnire.metrics import chamfer_distance
from omnire.raycast import first_hits

MODEL = BeamModel(np.array([4.0, 2.0, 1.0, 0.0, -1.0, -2.0, -4.0, -7.0, -10.0, -15.0]), 1.0, 120.0, 0.3, "toy")
PLANES = [(np.array([0.0, 0.0, 1.0]), -1.8), (np.array([-1.0, 0.0, 0.0]), -25.0)]
"""Ground z = -1.8 and a wall x = 25 (normal n, offset c: n . p = c)."""


def cast_planes(origins: np.ndarray, directions: np.ndarray, planes=PLANES) -> np.ndarray:
    """(R,) distance to the nearest of ``planes`` along each ray (NaN when none ahead)."""
    best = np.full(len(origins), np.inf)
    for n, c in planes:
        denom = directions @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - origins @ n) / denom
        best = np.where((t > 1e-9) & (t < best), t, best)
    return np.where(np.isfinite(best) & (best <= MODEL.max_range), best, np.nan)


def track(speed: float = 10.0, yaw_rate: float = 0.2, k: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A sensor 1.8 m above the ground driving along x and turning: (k,) times, (k, 4, 4) poses."""
    times = 100.0 + 0.1 * np.arange(k)
    poses = np.stack([rigid(rot_z(np.float64(yaw_rate * (t - 100.0))), (speed * (t - 100.0), 0.0, 0.0)) for t in times])
    return times, poses


def spinning_sweep(times: np.ndarray, poses: np.ndarray, frame: int, drop: float = 0.0, seed: int = 0,
                   planes=PLANES):
    """One revolution ending at ``times[frame]``, each ray fired at its column's time from the
    pose then: world points (N, 3), times (N,), beams (N,) and the kept mask (B*A,)."""
    d, beam, col = MODEL.directions()
    t = times[frame] - 0.1 + 0.1 * (col + 0.5) / MODEL.num_azimuths
    pose = interpolate_poses(times, poses, t)
    o, dw = pose[:, :3, 3], np.einsum("rij,rj->ri", pose[:, :3, :3], d)
    r = cast_planes(o, dw, planes)
    kept = np.isfinite(r) & (np.random.default_rng(seed).random(len(r)) >= drop)
    return (o + dw * r[:, None])[kept], t[kept], beam[kept].astype(np.int16), kept


# ---------------------------------------------------------------------------- geometry helpers
def test_extend_poses_continues_constant_velocity_and_turn_rate():
    times, poses = track(k=4)
    known, ext = extend_poses(times, poses, 0.05)
    assert len(known) == 6 and np.allclose(known[[0, -1]], [times[0] - 0.05, times[-1] + 0.05])
    for t, P in ((known[0], ext[0]), (known[-1], ext[-1])):
        exact = rigid(rot_z(np.float64(0.2 * (t - 100.0))), (10.0 * (t - 100.0), 0.0, 0.0))
        np.testing.assert_allclose(P, exact, atol=1e-12)
    with pytest.raises(ValueError, match="K >= 2"):
        extend_poses(times[:1], poses[:1], 0.1)


def test_interpolated_rotations_equal_the_per_query_slerp():
    """The numpy path of interpolate_rotations takes each distinct bracket's relative rotation
    once and applies Rodrigues' formula per query: the per-query quaternion SLERP to rounding
    (known samples returned as they are, bit for bit)."""
    rng = np.random.default_rng(5)
    R = axis_angle_to_rotmat(rng.normal(size=(30, 3)))
    known = np.cumsum(rng.uniform(0.05, 0.2, 30))
    query = np.concatenate([rng.uniform(known[0] - 1, known[-1] + 1, 5000), known])
    i0, i1, w = bracket(known, query)
    slow = R[i0].copy()
    mix = w > 0
    slow[mix] = slerp_rotmats(R[i0][mix], R[i1][mix], np.ascontiguousarray(w[mix]))
    np.testing.assert_allclose(interpolate_rotations(R, i0, i1, w), slow, rtol=0, atol=1e-12)
    assert np.array_equal(interpolate_rotations(R, i0, i1, w)[-30:], R)


def test_first_hits_per_ray_origins_against_planes():
    verts = np.array([[25.0, -100, -50], [25.0, 100, -50], [25.0, 0, 150]])  # the wall x = 25
    rng = np.random.default_rng(1)
    origins = rng.uniform(-2, 2, (200, 3))
    d = np.column_stack([np.ones(200), rng.uniform(-0.5, 0.5, (200, 2))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:5] *= -1  # pointing away: no hit
    hits = first_hits(verts, np.array([[0, 1, 2]]), origins, d)
    exact = (25.0 - origins[:, 0]) / d[:, 0]
    np.testing.assert_allclose(hits.distance[5:], exact[5:], rtol=1e-12)
    np.testing.assert_allclose(hits.cos_incidence[5:], d[5:, 0], rtol=1e-12)
    assert (hits.face[:5] == -1).all() and np.isnan(hits.distance[:5]).all() and (hits.face[5:] == 0).all()


def test_chamfer_distance_is_the_brute_force_one():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3)) + 0.3
    d = torch.cdist(torch.from_numpy(a), torch.from_numpy(b))
    expect = float(d.min(1).values.mean() + d.min(0).values.mean())
    assert chamfer_distance(a, b) == pytest.approx(expect, rel=1e-12)
    assert chamfer_distance(torch.from_numpy(a).float(), torch.from_numpy(b).float()) == pytest.approx(expect, rel=1e-6)
    assert np.isnan(chamfer_distance(a[:0], b))


# ---------------------------------------------------------------------------- recorded rays
def test_sweep_rays_are_the_beam_grid_with_the_missing_returns():
    times, poses = track()
    pts, t, beams, kept = spinning_sweep(times, poses, 3, drop=0.2)
    rays = sweep_rays(pts, t, times, poses, intensity=np.linspace(0, 1, len(pts)), beams=beams, model=MODEL)
    B, A = MODEL.num_beams, MODEL.num_azimuths
    assert len(rays) == B * A and rays.drops_known
    assert (rays.returned == kept).all()  # every missing return found, in its cell
    np.testing.assert_allclose(rays.points(), pts, atol=1e-9)
    np.testing.assert_allclose(rays.intensity[kept], np.linspace(0, 1, len(pts)), atol=1e-6)
    # A missing return points along its beam at its column's azimuth, from the sensor then.
    _, az, el = spherical(rays.local_directions)
    np.testing.assert_allclose(el, MODEL.elevations_deg[rays.beam], atol=1e-6)
    dcol = (az - rays.column * MODEL.azimuth_resolution_deg + 180) % 360 - 180
    assert np.abs(dcol).max() < 1e-6
    true_t = times[3] - 0.1 + 0.1 * (rays.column + 0.5) / A
    assert np.abs(rays.times - true_t).max() < 1e-9
    np.testing.assert_allclose(rays.origins, interpolate_poses(times, poses, true_t)[:, :3, 3], atol=1e-9)
    plain = sweep_rays(pts, t, times, poses)  # without beams: one ray per return, drops unknown
    assert len(plain) == len(pts) and not plain.drops_known and plain.returned.all()
    np.testing.assert_allclose(plain.points(), pts, atol=1e-9)
    with pytest.raises(SceneDataError, match="sweep_rays"):
        sweep_rays(pts[:, :2], t, times, poses)


# ---------------------------------------------------------------------------- metrics
def brute_force_metrics(pred_r, pred_i, pred_p, rays, boxes, thr=0.5) -> dict:
    out: dict = {}
    errs, rels, sq, inside = [], [], [], {"vehicle": [], "human": []}
    tp = fp = fn = tn = 0
    for k in range(len(rays)):
        answered = pred_p[k] <= thr and np.isfinite(pred_r[k])
        if rays.returned[k] and answered:
            e = abs(pred_r[k] - rays.range[k])
            errs.append(e)
            rels.append(e / rays.range[k])
            p = rays.origins[k] + rays.directions[k] * rays.range[k]
            for category in inside:
                for box in boxes:
                    local = np.linalg.inv(box.box_to_world) @ np.append(p, 1.0)
                    if box.category == category and all(abs(local[j]) <= box.size[j] / 2 for j in range(3)):
                        inside[category].append(e)
                        break
        if rays.returned[k] and answered and np.isfinite(pred_i[k]) and np.isfinite(rays.intensity[k]):
            sq.append((pred_i[k] - rays.intensity[k]) ** 2)
        drop, said = not rays.returned[k], pred_p[k] > thr
        tp += drop and said
        fp += said and not drop
        fn += drop and not said
        tn += not drop and not said
    out["median_abs_range_error"], out["mean_abs_range_error"] = np.median(errs), np.mean(errs)
    out["mean_relative_range_error"] = np.mean(rels)
    out["intensity_rmse"] = np.sqrt(np.mean(sq))
    out["drop_accuracy"] = (tp + tn) / len(rays)
    out["drop_f1"] = 2 * tp / (2 * tp + fp + fn)
    for c, e in inside.items():
        out[f"{c}_median_abs_range_error"], out[f"{c}_mean_abs_range_error"] = np.median(e), np.mean(e)
    pred = [rays.origins[k] + rays.directions[k] * pred_r[k] for k in range(len(rays))
            if pred_p[k] <= thr and np.isfinite(pred_r[k])]
    gt = [rays.origins[k] + rays.directions[k] * rays.range[k] for k in range(len(rays)) if rays.returned[k]]
    out["chamfer"] = (np.mean([min(np.linalg.norm(p - g) for g in gt) for p in pred])
                      + np.mean([min(np.linalg.norm(p - g) for p in pred) for g in gt]))
    return out


def test_lidar_metrics_equal_the_brute_force_ones():
    times, poses = track()
    pts, t, beams, _ = spinning_sweep(times, poses, 2, drop=0.3, seed=3)
    rng = np.random.default_rng(4)
    rays = sweep_rays(pts, t, times, poses, intensity=rng.random(len(pts)), beams=beams, model=MODEL)
    keep = np.zeros(len(rays), bool)
    keep[rng.choice(len(rays), 600, replace=False)] = True  # a small sweep keeps the brute force quick
    rays = type(rays)(**{k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in vars(rays).items()})
    R = len(rays)
    pred_r = np.where(rays.returned, rays.range, 20.0) + rng.normal(0, 0.3, R)
    pred_r[rng.random(R) < 0.1] = np.nan  # rays the renderer gives no range
    pred_i = rng.random(R)
    pred_p = np.clip(np.where(rays.returned, 0.2, 0.8) + rng.normal(0, 0.3, R), 0, 1)
    ground = rays.points()[np.argsort(rays.range[rays.returned])[5]]  # a box around some returns
    boxes = [Box(rigid(axis_angle_to_rotmat(np.array([0, 0, 0.4])), ground), np.array([8.0, 4.0, 3.0]), "vehicle"),
             Box(rigid(t=rays.points()[-3]), np.array([3.0, 3.0, 3.0]), "human")]
    got = lidar_metrics(RenderedSweep(pred_r, pred_i, pred_p), rays, boxes)
    expect = brute_force_metrics(pred_r, pred_i, pred_p, rays, boxes)
    for key, value in expect.items():
        assert got[key] == pytest.approx(value, rel=1e-9), key
    assert got["vehicle_returns"] > 3 and got["human_returns"] > 0 and got["returns"] == rays.returned.sum()
    answered = np.isfinite(pred_r) & (pred_p <= 0.5)
    assert got["range_coverage"] == pytest.approx(np.mean(answered[rays.returned]))
    mean = mean_metrics([got, got])
    assert mean["rays"] == 2 * R and mean["chamfer"] == pytest.approx(got["chamfer"])
    with pytest.raises(SceneDataError, match="drop_probability"):
        RenderedSweep(pred_r, pred_i, pred_p + 1.0)
    with pytest.raises(SceneDataError, match="rays"):
        lidar_metrics(RenderedSweep(pred_r[:-1], pred_i[:-1], pred_p[:-1]), rays)


def plane_render(sweep, path: SensorPath, sectors: int) -> LidarRender:
    """An exact renderer of :data:`PLANES` with ``Reconstruction.render_sweep``'s geometry:
    each time sector's rays cast from the sensor's pose at the sector's middle time."""
    rng = np.full(len(sweep), np.nan)
    for sector in sectors_of(sweep, path, sectors, dtype=torch.float64):
        pose, rows = sector.rays.sensor_to_world.numpy(), sector.index.numpy()
        directions = sweep.local_directions[rows] @ pose[:3, :3].T
        rng[rows] = cast_planes(np.broadcast_to(pose[:3, 3], directions.shape), directions)
    hit = torch.from_numpy(np.isfinite(rng)).double()
    r = torch.from_numpy(np.nan_to_num(rng, nan=MODEL.max_range))
    return LidarRender(r, r, torch.zeros(len(sweep), dtype=torch.float64), 1.0 - hit, hit)


def test_held_out_sweep_is_scored_from_the_poses_its_sectors_are_cast_from():
    """A sensor at 10 m/s rendered in 4 time sectors: a perfect render scores zero range
    error and Chamfer distance once the recorded rays are re-aimed from the sectors' poses
    (score_sweep); scored against the rays as fired, the same render is centimetres off on
    the wall ahead (each sector's origin is up to 12.5 cm behind or ahead of where its rays
    were fired)."""
    times, poses = track(k=6)
    pts, t, beams, kept = spinning_sweep(times, poses, 3)
    rays = sweep_rays(pts, t, times, poses, beams=beams, model=MODEL)
    path = SensorPath(times, poses)
    scored = score_sweep(plane_render, rays, path, 4)
    assert scored["median_abs_range_error"] < 1e-9 and scored["chamfer"] < 1e-3
    assert scored["range_coverage"] > 0.99 and scored["drop_accuracy"] > 0.99
    unaimed = lidar_metrics(rendered_sweep(plane_render(rays, path, 4)), rays)
    assert unaimed["mean_abs_range_error"] > 0.005  # the wall ahead (the ground is level: the same range)
    assert scored["mean_abs_range_error"] < 1e-3


# ---------------------------------------------------------------------------- baselines
def test_nearest_sweep_of_the_same_sweep_is_exact_and_matches_brute_force():
    times, poses = track()
    pts, t, beams, kept = spinning_sweep(times, poses, 3, drop=0.2)
    value = np.linspace(0, 1, len(pts))
    rays = sweep_rays(pts, t, times, poses, intensity=value, beams=beams, model=MODEL)
    out = nearest_sweep_render(pts, value, rays, times, poses, cell_tolerance_deg(MODEL))
    # Away from the seam of the revolution (where the moving sensor sees the first column's
    # returns again at the end) each ray gets back its own return.
    inner = (rays.column >= 2) & (rays.column <= MODEL.num_azimuths - 3)
    assert (np.isfinite(out.range) == kept)[inner].all() and (out.drop_probability == ~kept)[inner].all()
    k = kept & inner
    np.testing.assert_allclose(out.range[k], rays.range[k], atol=1e-9)
    np.testing.assert_allclose(out.intensity[k], rays.intensity[k], atol=1e-6)
    # Another frame's sweep seen from here, against a brute-force search over rays (a static
    # sensor, so no time enters): each ray takes the nearest return within the tolerance.
    still_t, still = times, np.repeat(poses[3:4], len(times), 0)
    other, _, _, _ = spinning_sweep(times, poses, 1, drop=0.5, seed=7)
    target = sweep_rays(pts, t, still_t, still, beams=beams, model=MODEL)
    out = nearest_sweep_render(other, None, target, still_t, still, 0.4)
    local = (other - poses[3, :3, 3]) @ poses[3, :3, :3]
    rng = np.linalg.norm(local, axis=1)
    angle = np.degrees(np.arccos(np.clip((local / rng[:, None]) @ target.local_directions.T, -1, 1)))  # (N, R)
    for k in range(len(target)):
        mine = angle[:, k] < 0.4
        assert (np.isnan(out.range[k]) if not mine.any() else out.range[k] == pytest.approx(rng[mine].min()))
    assert np.isfinite(out.range).sum() > 500


def test_mesh_of_training_sweeps_renders_the_ground_from_a_new_pose():
    """Triangles between returns on the ground lie on it: from a pose between the training
    ones, every ray of the beams that meet the ground within the mesh's reach hits it at the
    exact range. (The far rings at -1 and -2 degrees, 103 m and 51 m away, are joined by
    triangles longer than their range and left out: grazing ground stays uncovered.)"""
    ground = PLANES[:1]
    times, poses = track(speed=5.0, yaw_rate=0.1, k=8)
    train = []
    for f in (1, 2, 4, 5, 6):
        pts, t, beams, _ = spinning_sweep(times, poses, f, planes=ground)
        train.append(sweep_rays(pts, t, times, poses, intensity=np.full(len(pts), 0.25), beams=beams, model=MODEL))
    mesh = lidar_mesh(train, MODEL)
    pts, t, beams, kept = spinning_sweep(times, poses, 3, planes=ground)  # held out, between training poses
    target = sweep_rays(pts, t, times, poses, beams=beams, model=MODEL)
    out = mesh_render(mesh, target)
    hit = np.isfinite(out.range)
    el = MODEL.elevations_deg[target.beam]
    reach = kept & (el <= -7.0)  # ground within 15 m: inside every training sweep's mesh
    assert reach.sum() == 3 * MODEL.num_azimuths and hit[reach].all()
    edge = kept & (el == -4.0)  # the outermost ring kept (26 m): a few rays fall past its edge
    assert hit[edge].mean() > 0.95
    both = hit & kept
    np.testing.assert_allclose(out.range[both], target.range[both], rtol=1e-9)
    assert not hit[~kept].any()  # rays above the horizon: nothing to hit
    assert (out.intensity[hit] == 0.25).all() and (out.drop_probability == ~hit).all()


def test_triangles_across_a_depth_jump_are_dropped():
    times, poses = track(speed=0.0, yaw_rate=0.0)
    d, beam, col = MODEL.directions()
    r = np.where(col % 90 < 45, 10.0, 40.0)  # a step in range every 45 degrees of azimuth
    o = poses[0, :3, 3]
    t = np.full(len(d), times[0])
    rays = sweep_rays(o + d * r[:, None], t, times, poses, beams=beam.astype(np.int16), model=MODEL)
    tri = sweep_triangles(rays, MODEL)
    ranges = rays.range[tri]
    assert (ranges.max(1) - ranges.min(1) < 1e-9).all()  # none bridges 10 m and 40 m
    assert len(tri) == 2 * (MODEL.num_beams - 1) * (MODEL.num_azimuths - 8)  # all others kept


def test_triangles_of_a_pandar64_sized_grid():
    """64 beams x 1800 columns (more cells than an int16 beam index times the column count
    holds): inside a sphere around the sensor every 2 x 2 block gives its two triangles, and
    each joins neighbouring cells."""
    model = BeamModel(np.linspace(15.0, -25.0, 64), 0.2, 200.0, 0.3, "pandar64-sized")
    times, poses = track(speed=0.0, yaw_rate=0.0)
    d, beam, col = model.directions()
    rays = sweep_rays(poses[0, :3, 3] + 10.0 * d, np.full(len(d), times[0]), times, poses,
                      beams=beam.astype(np.int16), model=model)
    tri = sweep_triangles(rays, model)
    assert len(tri) == 2 * (model.num_beams - 1) * model.num_azimuths
    b, c = rays.beam[tri].astype(int), rays.column[tri]
    assert (b.max(1) - b.min(1) == 1).all()  # adjacent beams (the elevations are in order)
    assert np.isin((c.max(1) - c.min(1)) % (model.num_azimuths - 2), (0, 1)).all()  # adjacent columns, wrapping


def test_baseline_metrics_of_a_scene():
    """baseline_metrics scores a held-out sweep against the nearest training sweep (the
    earlier on a tie) and the mesh of the 4 nearest, with the scene's boxes at the frame."""
    times, poses = track(speed=5.0, yaw_rate=0.1, k=7)
    sweeps = [spinning_sweep(times, poses, f, drop=0.1, seed=f) for f in range(1, 7)]
    pts = [s[0].astype(np.float32) for s in sweeps]
    box = rigid(t=(25.0, 2.0, 0.0))  # a "vehicle" against the wall
    scene = SceneData(
        name="toy", cameras=[], frame_timestamps=times[1:], source_frames=np.arange(6),
        train_frames=np.array([0, 1, 3, 4, 5]), test_frames=np.array([2]),
        lidar=LidarSweeps(pts, poses[1:, :3, 3].copy(), intensity=[np.full(len(p), 0.5, np.float32) for p in pts],
                          times=[s[1] for s in sweeps], beams=[s[2] for s in sweeps], sensor_to_world=poses[1:],
                          beam_model=MODEL),
        tracks=[ActorTrack("car", "Car", "vehicle", np.repeat(box[None], 6, 0), np.array([4.0, 2.0, 3.0]),
                           np.ones(6, bool))])
    got = baseline_metrics(scene, scene.test_frames, scene.train_frames)
    target = recorded_sweep(scene, 2, grid_only=True)
    boxes = boxes_at(scene, 2)
    known, track_poses = extend_poses(times[1:], poses[1:], 0.2)
    near = nearest_sweep_render(pts[1], scene.lidar.intensity[1], target, known, track_poses, cell_tolerance_deg(MODEL))
    mesh = lidar_mesh([recorded_sweep(scene, g, grid_only=True) for g in (1, 3, 0, 4)], MODEL)
    for name, rendered in (("nearest_sweep", near), ("mesh", mesh_render(mesh, target))):
        expect = lidar_metrics(rendered, target, boxes)
        assert got[name].keys() == expect.keys()
        for key, value in expect.items():
            assert got[name][key] == pytest.approx(value, nan_ok=True), (name, key)
    assert got["mesh"]["vehicle_returns"] > 0 and got["mesh"]["median_abs_range_error"] < 0.05
