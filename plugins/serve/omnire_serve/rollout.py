"""Driving one episode with a driver (a callable ``(env, info) -> action``) and writing its
report: ``metrics.json`` (metrics.py) and ``episode.mp4`` (episode_video.py)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from omnire.api import atomic_write_text
from omnire_serve.episode_video import write_episode_video
from omnire_serve.metrics import episode_metrics


def rollout(env, driver: Callable, scenario: Optional[dict] = None, seed: int = 0,
            max_steps: int = 1000) -> tuple[list[dict], list[dict]]:
    """(observations, infos) of one episode, from the reset to the step that ended it."""
    obs, info = env.reset(seed=seed, options={"scenario": scenario} if scenario else None)
    frames, infos = [obs], [info]
    for _ in range(max_steps):
        obs, _, terminated, truncated, info = env.step(driver(env, info))
        frames.append(obs)
        infos.append(info)
        if terminated or truncated:
            break
    return frames, infos


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_report(output: Path, env, frames: list[dict], infos: list[dict], video: bool = True) -> dict:
    """Write ``metrics.json`` (the metrics and the ego's path) and ``episode.mp4`` into
    ``output``; returns the metrics."""
    output.mkdir(parents=True, exist_ok=True)
    metrics = episode_metrics(infos, env.config.ego_size, env.dt)
    path = [{"t": i["t"], "x": i["ego"]["x"], "y": i["ego"]["y"], "yaw": i["ego"]["yaw"], "speed": i["ego"]["speed"],
             "event": i["event"]} for i in infos]
    atomic_write_text(output / "metrics.json", json.dumps(_plain({**metrics, "ego_path": path}), indent=1) + "\n")
    if video:
        write_episode_video(output / "episode.mp4", frames, infos, env.corridor, env.config.ego_size, 1.0 / env.dt)
    return metrics
