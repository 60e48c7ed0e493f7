"""Closed-loop metrics of one episode, in the spirit of NeuroNCAP's and HUGSIM's scores,
from the environment's per-step ``info``:

- ``collision``: the first actor the ego touched (id, class), the time and the ego's speed
  then; None without one;
- ``min_time_to_collision``: the smallest time (s) until the ego's front would reach the
  nearest actor box in its path (boxes reaching into the ego's width ahead of it,
  boxes.gap_ahead), at the two's speeds along its heading at each step (None: never closing in);
- ``progress``: metres driven along the route and the fraction of its length;
- comfort: the largest |jerk| (m/s^3, from the ego's accelerations) and |lateral
  acceleration| (m/s^2: speed x yaw rate);
- ``score``: 5 without a collision, else 4 x (1 - impact speed / initial speed) clipped to
  [0, 4] (NeuroNCAP's scale: a collision at a reduced speed scores above 0, none scores 5).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from omnire_serve.boxes import gap_ahead


def time_to_collision(prev: dict, info: dict, ego_size: tuple[float, float, float], dt: float) -> Optional[float]:
    """Seconds until the ego's front reaches the nearest actor box in its path at ``info``'s
    moment, at constant speeds along the ego's heading (actor speeds from ``prev``), or None."""
    L, W = ego_size[0], ego_size[1]
    before = {b["id"]: np.asarray(b["pose"]) for b in prev["actors"]}
    ego = info["ego"]
    v_ego = ego["speed"]
    best = None
    for b in info["actors"]:
        pose = np.asarray(b["pose"])
        gap = gap_ahead((ego["x"], ego["y"]), ego["yaw"], L, W, pose, np.asarray(b["size"]))
        if gap is None:
            continue
        v_actor = 0.0
        if b["id"] in before:
            yaw = info["ego"]["yaw"]
            d = pose[:2, 3] - before[b["id"]][:2, 3]
            v_actor = (d[0] * math.cos(yaw) + d[1] * math.sin(yaw)) / dt
        closing = v_ego - v_actor
        if closing > 1e-3:
            ttc = max(gap, 0.0) / closing
            best = ttc if best is None else min(best, ttc)
    return best


def episode_metrics(infos: list[dict], ego_size: tuple[float, float, float], dt: float) -> dict:
    """The metrics (module docstring) of the infos of one episode (reset's first)."""
    first, last = infos[0], infos[-1]
    speeds = np.array([i["ego"]["speed"] for i in infos])
    accels = np.array([i["ego"]["accel"] for i in infos[1:]]) if len(infos) > 1 else np.zeros(0)
    yaws = np.unwrap(np.array([i["ego"]["yaw"] for i in infos]))
    jerk = np.abs(np.diff(accels)) / dt if len(accels) > 1 else np.zeros(0)
    lateral = np.abs(speeds[1:] * np.diff(yaws) / dt) if len(infos) > 1 else np.zeros(0)
    ttcs = [time_to_collision(a, b, ego_size, dt) for a, b in zip(infos[:-1], infos[1:])]
    ttcs = [t for t in ttcs if t is not None]
    collision = None
    hit = next((i for i in infos if i["event"] == "collision"), None)
    if hit is not None:
        other = hit["collided_with"]
        collision = {"actor": other["id"], "class": other["class"], "t": hit["t"], "ego_speed": hit["ego"]["speed"]}
    length = first["route"]["length"]
    driven = max(0.0, last["route"]["progress"] - first["route"]["progress"])
    v0 = max(float(speeds[0]), 1e-6)
    score = 5.0 if collision is None else float(np.clip(4.0 * (1.0 - collision["ego_speed"] / v0), 0.0, 4.0))
    return {
        "steps": len(infos) - 1,
        "seconds": float(last["t"] - first["t"]),
        "end": last["event"],
        "collision": collision,
        "min_time_to_collision": min(ttcs) if ttcs else None,
        "progress": {"metres": driven, "route_length": length, "fraction": driven / length if length > 0 else 0.0},
        "comfort": {"max_abs_jerk": float(jerk.max()) if len(jerk) else 0.0,
                    "max_abs_lateral_accel": float(lateral.max()) if len(lateral) else 0.0,
                    "max_abs_accel": float(np.abs(accels).max()) if len(accels) else 0.0},
        "mean_speed": float(speeds.mean()),
        "score": score,
    }
