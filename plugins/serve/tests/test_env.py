"""The gymnasium environment on the tiny demo run: gymnasium's checker, the same episode in
process and through the server, the lane-keeping episode to the route's end, and the
braking scenario (a driver that ignores the car ahead collides, one that brakes does not)."""
from __future__ import annotations

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from omnire_serve.client import OmnireClient
from omnire_serve.controllers import LaneKeeper
from omnire_serve.env import DrivingEnv, EnvConfig
from omnire_serve.transport import HttpTransport, LocalTransport

WHITE_CAR = "8ac00bad-822c-4040-b9a2-31424dbcd486"
BRAKING = {"actor": [{"track": WHITE_CAR, "stop_at": 0.4, "brake": 0.4}]}
SMALL = EnvConfig(cameras=("front_camera",), size=(48, 27))


def drive(env: DrivingEnv, driver, scenario=None, max_steps: int = 100) -> list[dict]:
    """Infos of one episode, from the reset to the step that ended it."""
    obs, info = env.reset(seed=0, options={"scenario": scenario} if scenario else None)
    infos = [info]
    for _ in range(max_steps):
        obs, reward, terminated, truncated, info = env.step(driver(env, info))
        infos.append(info)
        if terminated or truncated:
            break
    return infos


def test_check_env(served):
    check_env(DrivingEnv(LocalTransport(served), SMALL), skip_render_check=True)
    check_env(DrivingEnv(LocalTransport(served), EnvConfig(cameras=("front_camera",), size=(48, 27),
                                                           action="waypoints")), skip_render_check=True)


def test_same_episode_in_process_and_through_the_server(served, server):
    local = DrivingEnv(LocalTransport(served), SMALL)
    remote = DrivingEnv(HttpTransport(OmnireClient(server.url, session="env")), SMALL)
    actions = [np.array([1.0, 0.05], np.float32), np.array([-2.0, -0.1], np.float32), np.array([0.5, 0.0], np.float32)]
    for env in (local, remote):
        env.reset(seed=3, options={"scenario": BRAKING})
    for a in actions:
        o1, r1, t1, u1, i1 = local.step(a)
        o2, r2, t2, u2, i2 = remote.step(a)
        assert np.array_equal(o1["front_camera"], o2["front_camera"])
        assert (r1, t1, u1) == (r2, t2, u2)
        assert np.allclose(i1["ego"]["pose"], i2["ego"]["pose"])
        assert [b["id"] for b in i1["actors"]] == [b["id"] for b in i2["actors"]]


def test_lane_keeping_reaches_the_route_end(served):
    env = DrivingEnv(LocalTransport(served), SMALL)
    infos = drive(env, LaneKeeper(speed=7.0))
    assert infos[-1]["event"] == "route_end", infos[-1]["event"]
    assert all(i["event"] != "collision" for i in infos)
    assert max(abs(i["route"]["lateral"]) for i in infos) < 0.5


def test_braking_car_ahead(served):
    env = DrivingEnv(LocalTransport(served), SMALL)
    ignoring = drive(env, LaneKeeper(speed=7.0), BRAKING)
    assert ignoring[-1]["event"] == "collision"
    assert ignoring[-1]["collided_with"]["id"] == WHITE_CAR
    braking = drive(env, LaneKeeper(speed=7.0, brake_for_lead=True), BRAKING)
    assert all(i["event"] != "collision" for i in braking)
    assert braking[-1]["event"] == "log_end" and braking[-1]["ego"]["speed"] < 0.5
    # the same driver without the edit: the car drives on, the route is completed
    assert drive(env, LaneKeeper(speed=7.0, brake_for_lead=True))[-1]["event"] == "route_end"


def test_bad_actions_are_refused(served):
    env = DrivingEnv(LocalTransport(served), SMALL)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(np.array([np.nan, 0.0], np.float32))


def test_episode_report(served, tmp_path):
    """metrics.json and episode.mp4 of the braking scenario, ignored and handled."""
    import json

    from omnire.io.video import read_mp4
    from omnire_serve.rollout import rollout, write_report

    env = DrivingEnv(LocalTransport(served), EnvConfig(size=(96, 54)))
    frames, infos = rollout(env, LaneKeeper(speed=7.0), BRAKING)
    metrics = write_report(tmp_path / "ignored", env, frames, infos)
    saved = json.loads((tmp_path / "ignored" / "metrics.json").read_text())
    assert saved["collision"]["actor"] == WHITE_CAR and saved["collision"]["ego_speed"] > 3.0
    assert saved["score"] == metrics["score"] < 4.0 and saved["min_time_to_collision"] == 0.0
    assert len(saved["ego_path"]) == len(infos)
    video, fps = read_mp4(tmp_path / "ignored" / "episode.mp4")
    assert len(video) == len(infos) and fps == pytest.approx(10.0, abs=0.1)
    assert video.shape[2] == 3 * 96  # the three cameras side by side, the bird's-eye view below
    frames, infos = rollout(env, LaneKeeper(speed=7.0, brake_for_lead=True), BRAKING)
    handled = write_report(tmp_path / "braking", env, frames, infos, video=False)
    assert handled["collision"] is None and handled["score"] == 5.0
    assert handled["min_time_to_collision"] > 0.5 and handled["comfort"]["max_abs_accel"] <= 8.0 + 1e-6
