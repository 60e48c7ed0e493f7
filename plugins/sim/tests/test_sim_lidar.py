"""LiDAR rendered with a scenario's edits (Reconstruction.render_sweep with the Simulation as
its edits): a removed car's points vanish, a moved car's points go with its box, an actor
inserted from another run casts points on its box. The street of sim_scene.py, built with
LiDAR features (untrained Gaussians: every test compares sweeps of the same Gaussians)."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from omnire.api import (BeamModel, LidarConfig, LidarRender, Reconstruction, beam_model_sweep, fixed_path,
                        sectors_of, spin_times, sweep_points)
from omnire.observations import Observations
from omnire_sim import Simulation, parse_scenario
from sim_scene import small_omnire, street_scene

# The sensor 1.5 m above the tiny scene's ground (z = -1.5), at the cameras' start.
SENSOR = np.eye(4)
SENSOR[:3, 3] = (0.0, 0.0, 0.0)
BEAMS = BeamModel(np.linspace(-30.0, 5.0, 36), 0.5, 40.0, 0.3, "test")
MARGIN = 0.3  # metres around a box within which its points count as on it


def build_with_lidar(scene, plugins, seed: int = 0) -> Reconstruction:
    """The street's Gaussians as initialised, with LiDAR features; the background's voxels
    (and so its Gaussians) 0.2 m across, so that the ground's Gaussians, untrained, reach
    about 0.2 m above it."""
    method = small_omnire(plugins)
    nodes = dict(method.nodes)
    nodes["background"] = dataclasses.replace(nodes["background"], voxel_size=0.2)
    method = dataclasses.replace(method, nodes=nodes, rasterizer="cpu", lidar=LidarConfig(enabled=True))
    torch.manual_seed(seed)
    device = torch.device("cpu")
    return Reconstruction.build(method, scene, plugins, device, Observations(scene, device).images, seed=seed)


@pytest.fixture(scope="module")
def lidar_street(tmp_path_factory, plugins):
    torch.set_num_threads(1)
    return build_with_lidar(street_scene(tmp_path_factory.mktemp("lidar-street")), plugins)


def rendered(recon, text: str, frame: int = 2, assets=None):
    """(render, sweep) of every ray of BEAMS from SENSOR at ``frame`` with the scenario ``text``."""
    sim = Simulation(recon, parse_scenario(text, "test.toml"), assets=assets)
    sweep = beam_model_sweep(BEAMS, recon.time(frame).seconds)
    with torch.no_grad():
        return recon.render_sweep(sweep, fixed_path(SENSOR), 1, edits=sim), sweep


def points(recon, text: str, frame: int = 2, assets=None) -> np.ndarray:
    """(P, 3) the point cloud of :func:`rendered` (omnire.api.sweep_points)."""
    render, sweep = rendered(recon, text, frame, assets)
    p = sweep_points(render, sweep, fixed_path(SENSOR), 1)
    return np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64)


def in_box(p: np.ndarray, centre, size, margin: float = MARGIN, above_ground: float = 0.0) -> np.ndarray:
    """(N,) bool: inside the axis-aligned box (+ margin), and above its bottom by ``above_ground``."""
    lo, hi = np.asarray(centre) - np.asarray(size) / 2, np.asarray(centre) + np.asarray(size) / 2
    inside = np.all((p >= lo - margin) & (p <= hi + margin), axis=1)
    return inside & (p[:, 2] > lo[2] + above_ground)


CAR2_CENTRE, CAR2_SIZE = (9.0, -2.6, -0.75), (4.2, 1.8, 1.5)


def test_a_removed_cars_points_vanish(lidar_street):
    """Every ray that met car-2 (its point in the box, above the ground's Gaussians) goes
    further once car-2 is removed (the background behind appears) or returns nothing; what
    is left in the box above the ground are the few rays that graze the untrained, half
    transparent Gaussians of car-1's edge and the wall behind (their expected range lies
    between the two)."""
    text = '[[actor]]\ntrack = "car-2"\nremove = true\n'
    before, sweep = rendered(lidar_street, "")
    after, _ = rendered(lidar_street, text)
    ray_points = sweep.local_directions * before.range.numpy()[:, None] + SENSOR[:3, 3]
    met = (before.ray_drop.numpy() < 0.5) & in_box(ray_points, CAR2_CENTRE, CAR2_SIZE, 0.0, above_ground=0.3)
    further = (after.ray_drop.numpy() >= 0.5) | (after.range.numpy() > before.range.numpy() + 0.5)
    assert met.sum() > 50 and further[met].all()
    left = in_box(points(lidar_street, text), CAR2_CENTRE, CAR2_SIZE, 0.0, above_ground=0.3).sum()
    assert left < 0.05 * met.sum(), f"{left} points left in the removed car's box of {met.sum()}"


def test_a_moved_car_takes_its_points_along(lidar_street):
    offset = np.array([0.0, 6.5, 0.0])  # onto the empty left side of the road
    before = points(lidar_street, "")
    after = points(lidar_street, '[[actor]]\ntrack = "car-2"\noffset_world = [0.0, 6.5, 0.0]\n')
    new_centre = np.asarray(CAR2_CENTRE) + offset
    was = in_box(before, CAR2_CENTRE, CAR2_SIZE, 0.0, above_ground=0.3).sum()
    assert in_box(after, CAR2_CENTRE, CAR2_SIZE, 0.0, above_ground=0.3).sum() < 0.05 * was  # as for removal
    moved_there = in_box(after, new_centre, CAR2_SIZE, MARGIN, above_ground=0.3).sum()
    was_there = in_box(before, new_centre, CAR2_SIZE, MARGIN, above_ground=0.3).sum()
    assert moved_there > 20 + was_there


def test_an_inserted_actor_casts_points_on_its_box(lidar_street, plugins, tmp_path):
    """car-1 of the street (run A) inserted into a street without actors (run B): the points
    that differ from B's own sweep lie on the guest's box."""
    recon_b = build_with_lidar(street_scene(tmp_path / "b", with_actors=False), plugins, seed=3)
    centre, yaw = (6.0, 2.0, -0.75), 0.0
    text = (f'[[insert]]\nid = "guest"\nrun = "run-a"\ntrack = "car-1"\n'
            f'trajectory = [{{t = 0.0, x = {centre[0]}, y = {centre[1]}, z = {centre[2]}, yaw = {yaw}}}]\n')
    run_a = parse_scenario(text, "test.toml").resolve_path("run-a").resolve()
    size = lidar_street.scene.tracks[0].size
    assert in_box(points(recon_b, ""), centre, size, above_ground=0.3).sum() == 0  # nothing there but the ground
    assert in_box(points(recon_b, text, assets={run_a: lidar_street}), centre, size, above_ground=0.3).sum() > 20
    # ray by ray: the rays the guest stops (it adds at least 0.3 to their opacity and their
    # first surface, the median range, comes nearer) stop on its box. (Untrained, the guest's
    # Gaussians are sparse random points in its box: rays through a corner of it keep much of
    # their transmittance and land behind it, which is not its surface.)
    plain, sweep = rendered(recon_b, "")
    guest, _ = rendered(recon_b, text, assets={run_a: lidar_street})
    r0, r1 = plain.median_range.numpy(), guest.median_range.numpy()
    hit = (guest.ray_drop.numpy() < 0.5) & (guest.alpha.numpy() - plain.alpha.numpy() > 0.3) & (r1 < r0 - 0.05)
    on = in_box(sweep.local_directions[hit] * r1[hit, None] + SENSOR[:3, 3], centre, size)
    assert hit.sum() > 20 and on.mean() > 0.95, f"{on.mean():.3f} of {hit.sum()} new returns on the box"


@pytest.fixture(scope="module")
def demo_lidar_run(tmp_path_factory, plugins):
    """streetgs with LiDAR rendering on 4 frames of the demo scene (PandaSet: sensor poses and
    per-point times, so sweeps render in time sectors), 2 steps."""
    from conftest import DEMO_SCENE

    if not DEMO_SCENE.is_dir():
        pytest.skip("demo scene (data/demo/pandaset_002) not in this checkout")
    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    root = tmp_path_factory.mktemp("lidar-runs")
    argv = ["streetgs", "pandaset", "--data", str(DEMO_SCENE), "--end-frame", "4", "--holdout-every", "2",
            "--scale", "0.25", "--method.nodes.background.max-lidar-points", "3000",
            "--method.nodes.background.num-far-points", "300", "--trainer.max-steps", "2", "--trainer.no-progress",
            "--trainer.eval-train-views", "1", "--trainer.threads", "1", "--trainer.output-dir", str(root),
            "--trainer.run-name", "demo", "--method.lidar.enabled", "--method.lidar.every", "1",
            "--method.lidar.rays-per-step", "4000"]
    Trainer(parse_train_args(argv, plugins), plugins, argv=argv).train()
    return root / "demo"


def test_sim_lidar_writes_a_point_cloud_per_frame_without_the_removed_car(demo_lidar_run, plugins, tmp_path):
    from omnire_sim.cli import SimArgs, run_sim, sim_sweep

    recon = Reconstruction.from_run(demo_lidar_run, plugins)
    node = recon.actor_nodes()["rigid"]
    state = node.state_at(recon.time(1))

    def in_car(k: int, cloud) -> int:
        """Points of ``cloud`` inside car k's box at frame 1, 0.3 m above its bottom."""
        p = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1).astype(np.float64)
        local = (p - state.t[k].detach().double().numpy()) @ state.R[k].detach().double().numpy()
        half = node.half_sizes[int(state.ids[k])].detach().double().numpy()
        return int((np.all(np.abs(local) <= half, axis=1) & (local[:, 2] > -half[2] + 0.3)).sum())

    with torch.no_grad():  # the recorded scene's sweep: the car the LiDAR sees most of
        recorded = sim_sweep(Simulation(recon, parse_scenario("", "empty.toml")), recon.time(1))
    counts = [in_car(k, recorded) for k in range(len(state.ids))]
    k = int(np.argmax(counts))
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(f'[camera]\npath = "recorded"\nframes = [1]\n[[actor]]\n'
                        f'track = "{node.track_ids[int(state.ids[k])]}"\nremove = true\n')
    out = tmp_path / "sim"
    run_sim(SimArgs(demo_lidar_run, scenario, out, progress=False, lidar=True, video=False), plugins)
    manifest = json.loads((out / "manifest.json").read_text())
    ply, npz = manifest["frames"][0]["lidar"]
    cloud = np.load(out / npz)
    assert len(cloud["x"]) > 1000 and (out / ply).is_file() and np.isfinite(cloud["time"]).all()
    assert counts[k] > 10 and in_car(k, cloud) < 0.05 * counts[k], (counts[k], in_car(k, cloud))


def test_boxes_drawn_on_the_sweep_hold_its_actors_in_every_sector(lidar_street):
    """A sweep fired over the 0.1 s before frame 4 and rendered in 4 time sectors: with boxes
    at the frames' timestamps (``box_timing`` "frame") each sector meets the riding bike and
    the walking pedestrian where they were at its middle time, up to 0.35 m back; with boxes
    drawn where the sweep saw their actors ("sweep", as PandaSet's) every sector meets them
    at the sweep's end, frame 4: the same rays rendered sector by sector at frame 4."""
    recon = lidar_street
    end = recon.time(4).seconds
    spun = beam_model_sweep(BEAMS, end)
    times = spin_times(spun.azimuth_deg, end - 0.1, 0.1)
    times[np.argmax(times)] = end  # the last ray fires at the frame's timestamp
    spun = dataclasses.replace(spun, times=times)
    path = fixed_path(SENSOR)
    with torch.no_grad():
        sectors = sectors_of(spun, path, 4)
        at_end = LidarRender.cat([recon.render_lidar(s.rays, recon.time(4)) for s in sectors],
                                 torch.cat([s.index for s in sectors]))
        assert recon.scene.box_timing == "frame"
        frame_timed = recon.render_sweep(spun, path, 4)
        recon.scene.box_timing = "sweep"
        try:
            sweep_timed = recon.render_sweep(spun, path, 4)
        finally:
            recon.scene.box_timing = "frame"
    assert torch.equal(sweep_timed.range, at_end.range) and torch.equal(sweep_timed.ray_drop, at_end.ray_drop)
    moved = (frame_timed.range - at_end.range).abs() > 0.1
    assert int(moved.sum()) > 20  # the rays that met the bike or the pedestrian where they were earlier
