"""Rolling shutter (omnire/rollingshutter.py): a sweep from a moving, turning sensor,
rendered in time sectors, hits a static box at the ranges a per-ray ray cast records. The
box is ahead, across azimuth 0, where a sweep starts and ends: its two halves are scanned
0.1 s (1 m of travel) apart."""
import math

import numpy as np
import pytest
import torch
from scene_helpers import DEMO_SCENE

from omnire.api import RasterInputError, Splats, points_in_sensor_frame, spherical, spin_times, sweep_sectors
from omnire_rasterizer_torch import TorchRasterizer

SPEED, YAW_RATE, SWEEP = 10.0, 0.5, 0.1  # m/s along x, rad/s, seconds per revolution
BOX_LO, BOX_HI = np.array([5.0, -3.0, -1.5]), np.array([8.0, 3.0, 1.0])  # ahead, across the sweep's seam
SIGMA = 0.15


def sensor_pose(t: float) -> np.ndarray:
    """The sensor at time t: at (SPEED t, 0, 0), turned by YAW_RATE t about z."""
    yaw = YAW_RATE * t
    pose = np.eye(4)
    pose[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    pose[0, 3] = SPEED * t
    return pose


def box_splats() -> Splats:
    """Flat Gaussians (SIGMA wide, 1 mm thick) covering the six faces of the box."""
    means, quats = [], []
    q_of_axis = {0: [math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0],  # thin axis along x
                 1: [math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0],  # along y
                 2: [1.0, 0, 0, 0]}  # along z
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        U, V = np.meshgrid(np.arange(BOX_LO[u], BOX_HI[u] + 1e-9, SIGMA), np.arange(BOX_LO[v], BOX_HI[v] + 1e-9, SIGMA),
                           indexing="ij")
        for side in (BOX_LO[axis], BOX_HI[axis]):
            p = np.zeros((U.size, 3))
            p[:, axis], p[:, u], p[:, v] = side, U.ravel(), V.ravel()
            means.append(p)
            quats.append(np.tile(q_of_axis[axis], (U.size, 1)))
    means = torch.tensor(np.concatenate(means))
    M = len(means)
    scales = torch.tensor([[SIGMA, SIGMA, 1e-3]], dtype=torch.float64).repeat(M, 1)
    return Splats(means, torch.tensor(np.concatenate(quats)), scales,
                  torch.full((M,), 0.9, dtype=torch.float64), torch.ones(M, 1, dtype=torch.float64))


def ray_cast(az: np.ndarray, el: np.ndarray, times: np.ndarray):
    """Each ray from the sensor pose at its own time against the box (slab method): range
    (R,) (inf: no hit) and the hit's distance to the nearest edge of its face (R,)."""
    rng, margin = np.full(len(az), np.inf), np.zeros(len(az))
    for j in range(len(az)):
        pose = sensor_pose(times[j])
        a, e = math.radians(az[j]), math.radians(el[j])
        d = pose[:3, :3] @ [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
        o = pose[:3, 3]
        with np.errstate(divide="ignore"):
            t_lo, t_hi = (BOX_LO - o) / d, (BOX_HI - o) / d
        near, far = np.minimum(t_lo, t_hi), np.maximum(t_lo, t_hi)
        t_in, t_out = near.max(), far.min()
        if t_in <= t_out and t_in > 0:
            p = o + t_in * d
            face = int(np.argmax(near))
            others = [k for k in range(3) if k != face]
            rng[j] = t_in
            margin[j] = min(min(p[k] - BOX_LO[k], BOX_HI[k] - p[k]) for k in others)
    return rng, margin


def render_in_sectors(splats, az, el, times, sectors: int) -> np.ndarray:
    pose_times = np.array([0.0, SWEEP / 2, SWEEP])
    poses = np.stack([sensor_pose(t) for t in pose_times])
    median = torch.zeros(len(az), dtype=torch.float64)
    parts = sweep_sectors(torch.tensor(az), torch.tensor(el), times, pose_times, poses, 0.5, 80.0, sectors)
    assert sorted(torch.cat([p.index for p in parts]).tolist()) == list(range(len(az)))  # each ray once
    rast = TorchRasterizer()
    for part in parts:
        assert part.rays.sensor_to_world.dtype == torch.float64
        median[part.index] = rast.rasterize_lidar(splats, part.rays).median_range
    return median.numpy()


def test_sweep_from_a_moving_sensor_in_sectors_hits_the_box_at_the_recorded_ranges():
    az, el = np.meshgrid(np.arange(0.0, 360.0, 1.0), np.arange(-20.0, 4.0, 1.5), indexing="ij")  # a whole sweep
    az, el = az.ravel(), el.ravel()
    times = spin_times(az, 0.0, SWEEP)
    truth, margin = ray_cast(az, el, times)
    inside = margin > 3 * SIGMA  # away from the faces' edges, where the Gaussians overhang
    assert inside.sum() > 300
    splats = box_splats()
    err = {k: np.abs(render_in_sectors(splats, az, el, times, k) - truth)[inside] for k in (1, 36)}
    print("rolling shutter, median |range error| over", inside.sum(), "rays: one pose",
          f"{np.median(err[1]) * 100:.1f} cm, 36 sectors {np.median(err[36]) * 100:.2f} cm "
          f"(95th percentile {np.percentile(err[36], 95) * 100:.2f} cm)")
    assert np.median(err[36]) < 0.01 and np.percentile(err[36], 95) < 0.03
    assert np.median(err[1]) > 0.08  # one pose for the whole sweep misses the box by decimetres


def test_spin_times_and_bad_sectors():
    np.testing.assert_allclose(spin_times(np.array([0.0, 90.0, 359.0, -90.0]), 1.0, 0.1),
                               [1.0, 1.025, 1.0 + 0.1 * 359 / 360, 1.075])
    np.testing.assert_allclose(spin_times(np.array([90.0]), 0.0, 0.1, start_azimuth_deg=180.0,
                                          counter_clockwise=False), [0.025])
    az = torch.zeros(3, dtype=torch.float64)
    with pytest.raises(RasterInputError, match="times"):
        sweep_sectors(az, az, np.zeros(2), np.zeros(1), np.eye(4)[None], 0.0, 10.0, 4)
    with pytest.raises(RasterInputError, match="sectors: 0"):
        sweep_sectors(az, az, np.zeros(3), np.zeros(1), np.eye(4)[None], 0.0, 10.0, 0)
    assert sweep_sectors(az[:0], az[:0], np.zeros(0), np.zeros(1), np.eye(4)[None], 0.0, 10.0, 4) == []
    with pytest.raises(RasterInputError, match="probe_range"):
        sweep_sectors(az, az, np.zeros(3), np.zeros(1), np.eye(4)[None], 0.0, 10.0, 4, torch.ones(2))


def test_each_sector_carries_the_probes_of_its_rays():
    az = torch.linspace(0.0, 359.0, 50, dtype=torch.float64)
    probe = torch.arange(50, dtype=torch.float64) + 0.5
    parts = sweep_sectors(az, az * 0, spin_times(az.numpy(), 0.0, 0.1), np.zeros(1), np.eye(4)[None], 0.0, 10.0, 4,
                          probe)
    assert len(parts) == 4
    for part in parts:
        torch.testing.assert_close(part.rays.probe_range, probe[part.index])
    assert all(p.rays.probe_range is None for p in sweep_sectors(az, az * 0, np.zeros(50), np.zeros(1),
                                                                  np.eye(4)[None], 0.0, 10.0, 2))


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_a_recorded_pandaset_sweep_renders_back_in_sectors():
    """Real data: a PandaSet sweep's returns (every third), as small round Gaussians (0.1
    degrees wide at their range), rendered along the directions they were measured in from the
    sensor poses of their time: in 20 sectors the rays meet their own returns; with one pose
    for the sweep a third of them miss."""
    from omnire_pandaset.dataparser import PandasetConfig

    scene = PandasetConfig(data=DEMO_SCENE, cameras=("front_camera",), scale=0.25, end_frame=12).setup().parse()
    lidar, stamps = scene.lidar, np.asarray(scene.frame_timestamps)
    known = np.isfinite(lidar.sensor_to_world).all(axis=(1, 2))
    points, times = lidar.points[10][::3], lidar.times[10][::3]  # a third of the sweep: faster, as sparse
    rng, az, el = spherical(points_in_sensor_frame(points, times, stamps[known], lidar.sensor_to_world[known]))
    n = len(points)
    sigma = torch.tensor(np.maximum(rng * math.radians(0.1), 0.01))[:, None].repeat(1, 3)
    splats = Splats(torch.tensor(points, dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1).double(),
                    sigma, torch.full((n,), 0.9, dtype=torch.float64), torch.ones(n, 1, dtype=torch.float64))
    rast = TorchRasterizer()
    result = {}
    for sectors in (1, 20):
        median, alpha = np.zeros(n), np.zeros(n)
        for part in sweep_sectors(torch.tensor(az), torch.tensor(el), times, stamps[known], lidar.sensor_to_world[known],
                                  0.3, 200.0, sectors):
            out = rast.rasterize_lidar(splats, part.rays)
            median[part.index.numpy()], alpha[part.index.numpy()] = out.median_range.numpy(), out.alpha.numpy()
        result[sectors] = (np.mean(alpha > 0.5), np.median(np.abs(median - rng)))
    print("recorded sweep rendered back: one pose hits {:.1%}, median |error| {:.1f} cm; 20 sectors {:.1%}, {:.2f} cm"
          .format(result[1][0], result[1][1] * 100, result[20][0], result[20][1] * 100))
    assert result[20][0] > 0.98 and result[20][1] < 0.02
    assert result[1][0] < 0.85
