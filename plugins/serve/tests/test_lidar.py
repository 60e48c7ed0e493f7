"""POST /render_lidar on real ``omnire serve`` processes: the points equal
Reconstruction.render_lidar in this process for the same pose, time and edits (a run with
learned LiDAR features, and one without: range only); a car removed through /update_actors
leaves no points in its box; bad requests answer JSON naming the field and the server goes
on; the environment's LiDAR observation passes gymnasium's checker."""
from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from omnire.api import LidarRays
from omnire_serve.client import OmnireClient
from omnire_serve.env import LIDAR_OBSERVATION, DrivingEnv, EnvConfig
from omnire_serve.errors import RequestError
from omnire_serve.lidar import NPZ_MEDIA, beam_model_from
from omnire_serve.transport import HttpTransport, LocalTransport
from omnire_sim import Simulation, parse_scenario

from serve_helpers import hostile_request

WHITE_CAR = "8ac00bad-822c-4040-b9a2-31424dbcd486"
BEAMS = {"elevations_deg": np.linspace(-25.0, 3.0, 32).tolist(), "azimuth_step_deg": 0.5, "max_range": 80.0}
"""32 beams x 720 azimuths (fewer rays than the scene's own Pandar64 model, for speed)."""
SMALL_BEAMS = {"elevations_deg": np.linspace(-20.0, 2.0, 8).tolist(), "azimuth_step_deg": 2.0, "max_range": 80.0}


def expected_points(served, scenario_text: str, sensor: np.ndarray, seconds: float, beams: dict, overrides=None):
    """(points (P, 3), intensity, ray drop, kept ray indices) of Reconstruction.render_lidar
    in this process: every ray of ``beams`` from ``sensor``, the scene edited by the scenario;
    a ray returns below 0.5 ray-drop probability (1 - alpha without learned features)."""
    from omnire_serve.served import Episode

    recon = served.recon
    model = served.beam_model(beams)
    if overrides is None:
        sim = Simulation(recon, parse_scenario(scenario_text, "test.toml"), served.plugins)
    else:  # the edits an episode builds from /update_actors
        episode = Episode(served)
        episode.update_actors(overrides)
        sim = episode.sim
    rays = LidarRays.from_beam_model(torch.as_tensor(sensor, dtype=torch.float32), model)
    learned = recon.model.lidar_features is not None
    with torch.no_grad():
        r = recon.render_lidar(rays, sim.time(seconds), edits=sim, geometry_only=not learned)
    drop = r.ray_drop.numpy()
    kept = np.flatnonzero(drop < 0.5)
    az, el = np.deg2rad(rays.azimuth_deg.double().numpy()[kept]), np.deg2rad(rays.elevation_deg.double().numpy()[kept])
    direction = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    local = direction * r.range.double().numpy()[kept, None]
    world = local @ sensor[:3, :3].T + sensor[:3, 3]
    return world, r.intensity.numpy()[kept], drop[kept], kept


def sensor_at(served, frame: int, left: float = 0.0) -> np.ndarray:
    rig = served.rig[frame].copy()
    rig[:3, 3] += rig[:3, 1] * left
    return served.lidar_mounted(rig, float(served.seconds[frame]))


@pytest.mark.parametrize("which", ["learned", "range only"])
def test_points_equal_render_lidar_in_process(which, request):
    server = request.getfixturevalue("lidar_server" if which == "learned" else "server")
    served = request.getfixturevalue("lidar_served" if which == "learned" else "served")
    frame, seconds = 12, 1.25
    sensor = sensor_at(served, frame, left=1.5)
    stamp = served.start_us + 1_250_000
    scenario = {"actor": [{"track": WHITE_CAR, "stop_at": 1.0, "brake": 0.5}]}
    client = OmnireClient(server.url, session=f"lidar-{which.replace(' ', '-')}")
    client.set_scenario(scenario)
    meta, got = client.render_lidar(sensor, stamp, BEAMS)
    world, intensity, drop, kept = expected_points(
        served, f'[[actor]]\ntrack = "{WHITE_CAR}"\nstop_at = 1.0\nbrake = 0.5\n', sensor, seconds, BEAMS)
    assert meta["rays"] == 32 * 720 and meta["num_beams"] == 32 and meta["num_azimuths"] == 720
    assert meta["points"] == len(kept) > 1000 and meta["timestamp"] == stamp
    assert np.array_equal(got["beam"], kept // 720) and np.array_equal(got["column"], kept % 720)
    assert np.allclose(np.stack([got["x"], got["y"], got["z"]], 1), world, atol=1e-4)
    if which == "learned":
        assert meta["features"] == ["range", "intensity", "ray_drop"]
        assert np.allclose(got["intensity"], intensity, atol=1e-6) and np.allclose(got["ray_drop"], drop, atol=1e-6)
    else:
        assert meta["features"] == ["range"] and "intensity" not in got and "ray_drop" not in got
    # the same sweep as JSON, on request, for a small one
    small_meta, small = client.render_lidar(sensor, stamp, SMALL_BEAMS, fmt="json")
    world, _, _, kept = expected_points(
        served, f'[[actor]]\ntrack = "{WHITE_CAR}"\nstop_at = 1.0\nbrake = 0.5\n', sensor, seconds, SMALL_BEAMS)
    assert small_meta["points"] == len(kept) and np.array_equal(small["column"], kept % 180)
    assert np.allclose(np.stack([small["x"], small["y"], small["z"]], 1), world, atol=1e-4)
    r = httpx.post(server.url + "/render_lidar",
                   json={"pose": sensor.tolist(), "timestamp": stamp, "beam_model": BEAMS},
                   headers={"X-Omnire-Session": "lidar-media"}, timeout=300)
    assert r.status_code == 200 and r.headers["content-type"] == NPZ_MEDIA


def _in_box(xyz: np.ndarray, box: dict, above_bottom: float = 0.3) -> int:
    """Points of ``xyz`` (P, 3) inside ``box`` (pose, size), ``above_bottom`` metres above its floor."""
    pose, size = np.asarray(box["pose"]), np.asarray(box["size"])
    local = (xyz - pose[:3, 3]) @ pose[:3, :3]
    return int((np.all(np.abs(local) <= size / 2, axis=1) & (local[:, 2] > -size[2] / 2 + above_bottom)).sum())


def test_an_actor_removed_through_update_actors_leaves_no_points(lidar_server, lidar_served):
    """The actor the LiDAR sees most of at frame 8; left out of /update_actors (neurad-studio's
    removal), its box holds under 5% of its points, as the in-process render with that edit."""
    frame = 8
    sensor, stamp = sensor_at(lidar_served, frame), int(lidar_served.frame_us[frame])
    client = OmnireClient(lidar_server.url, session="lidar-remove")
    _, before = client.render_lidar(sensor, stamp, BEAMS)
    xyz = np.stack([before["x"], before["y"], before["z"]], 1).astype(np.float64)
    boxes = client.actors_at(stamp)
    counts = [_in_box(xyz, b) for b in boxes]
    seen = boxes[int(np.argmax(counts))]
    assert max(counts) > 10, counts
    actors = client.actors()
    left = [a for a in actors if a["uuid"] != seen["id"]]
    client.update_actors(left)
    _, after = client.render_lidar(sensor, stamp, BEAMS)
    xyz_after = np.stack([after["x"], after["y"], after["z"]], 1).astype(np.float64)
    assert _in_box(xyz_after, seen) < 0.05 * max(counts), (_in_box(xyz_after, seen), max(counts))
    world, _, _, _ = expected_points(lidar_served, "", sensor, float(lidar_served.seconds[frame]), BEAMS,
                                     overrides=json.loads(json.dumps(left)))
    assert np.allclose(xyz_after, world, atol=1e-4)
    client.reset()
    _, again = client.render_lidar(sensor, stamp, BEAMS)
    assert np.array_equal(again["x"], before["x"])


def test_bad_lidar_requests_answer_json_and_the_server_goes_on(server, served):
    client = httpx.Client(base_url=server.url, timeout=300)
    sensor, stamp = sensor_at(served, 3), int(served.frame_us[3])
    good = {"pose": sensor.tolist(), "timestamp": stamp, "beam_model": SMALL_BEAMS}
    nan_pose = [[float("nan")] * 4] + sensor.tolist()[1:]
    cases = [
        ("lidar: NaN pose", "pose", 400,
         {"content": json.dumps({**good, "pose": nan_pose}), "headers": {"content-type": "application/json"}}),
        ("lidar: huge beam count", "beam_model", 413,
         {"json": {**good, "beam_model": {**SMALL_BEAMS, "elevations_deg": np.linspace(-80, 80, 4000).tolist(),
                                          "azimuth_step_deg": 0.1}}}),
        ("lidar: time after the log", "timestamp", 400, {"json": {**good, "timestamp": served.end_us + 10**7}}),
        ("lidar: malformed JSON", "body", 400,
         {"content": b'{"pose": [[1, 0', "headers": {"content-type": "application/json"}}),
        ("lidar: NaN azimuth step", "beam_model.azimuth_step_deg", 400,
         {"content": json.dumps({**good, "beam_model": {**SMALL_BEAMS, "azimuth_step_deg": float("nan")}}),
          "headers": {"content-type": "application/json"}}),
        ("lidar: elevation of 95 degrees", "beam_model", 400,
         {"json": {**good, "beam_model": {**SMALL_BEAMS, "elevations_deg": [0.0, 95.0]}}}),
        ("lidar: unknown beam field", "beam_model.fov", 400,
         {"json": {**good, "beam_model": {**SMALL_BEAMS, "fov": 30}}}),
        ("lidar: JSON of a large sweep", "format", 413,
         {"json": {**good, "beam_model": {**BEAMS, "azimuth_step_deg": 0.25}, "format": "json"}}),
        ("lidar: unknown format", "format", 400, {"json": {**good, "format": "ply"}}),
        ("lidar: missing pose", "pose", 400, {"json": {"timestamp": stamp}}),
    ]
    for name, field, status, kw in cases:
        hostile_request(client, name, "POST", "/render_lidar", field, status, **kw)
        r = client.post("/render_lidar", json=good)  # the next good request still works
        assert r.status_code == 200 and r.headers["content-type"] == NPZ_MEDIA, name
    meta, _ = OmnireClient(server.url).render_lidar(sensor, stamp)  # the scene's own beam model: PandaSet's Pandar64
    assert (meta["num_beams"], meta["rays"]) == (64, 64 * 1800), meta


def test_beam_model_refusals():
    with pytest.raises(RequestError, match="no LiDAR beam model") as err:
        beam_model_from(None, None, 1000)
    assert err.value.field == "beam_model"
    with pytest.raises(RequestError, match="more than the limit") as err:
        beam_model_from({**SMALL_BEAMS, "azimuth_step_deg": 0.01}, None, 1000)
    assert err.value.status == 413
    model = beam_model_from(SMALL_BEAMS, None, 2000)
    assert (model.num_beams, model.num_azimuths, model.min_range) == (8, 180, 0.0)


def test_env_lidar_observation(lidar_served, lidar_server):
    config = EnvConfig(cameras=("front_camera",), size=(48, 27), lidar=True, beam_model=SMALL_BEAMS)
    check_env(DrivingEnv(LocalTransport(lidar_served), config), skip_render_check=True)
    local = DrivingEnv(LocalTransport(lidar_served), config)
    remote = DrivingEnv(HttpTransport(OmnireClient(lidar_server.url, session="env-lidar")), config)
    assert local.observation_space[LIDAR_OBSERVATION].shape == (8, 180)
    o1, _ = local.reset(seed=0)
    o2, _ = remote.reset(seed=0)
    action = np.array([1.0, 0.05], np.float32)
    o1, *_ = local.step(action)
    o2, *_ = remote.step(action)
    image = o1[LIDAR_OBSERVATION]
    assert image.dtype == np.float32 and (image > 0).mean() > 0.5 and image.max() <= 80.0
    assert np.array_equal(image, o2[LIDAR_OBSERVATION])
    cameras_only = DrivingEnv(LocalTransport(lidar_served), EnvConfig(cameras=("front_camera",), size=(48, 27)))
    assert LIDAR_OBSERVATION not in cameras_only.observation_space.spaces
    own = DrivingEnv(LocalTransport(lidar_served), EnvConfig(cameras=("front_camera",), size=(48, 27), lidar=True))
    assert own.observation_space[LIDAR_OBSERVATION].shape == (64, 1800)  # the scene's Pandar64 by default
