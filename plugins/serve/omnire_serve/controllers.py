"""Reference drivers for the environment (examples and tests): a lane keeper that follows
the route by pure pursuit at a set speed, optionally braking for the actor ahead."""
from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass
class LaneKeeper:
    """Bicycle actions (acceleration, steering rate) for a :class:`~omnire_serve.env.DrivingEnv`:
    steer towards the route point ``lookahead`` metres (at least; more when fast) ahead of
    the ego's projection; hold ``speed`` m/s. ``brake_for_lead``: also brake for an actor box
    in the ego's path ahead, to stop ``stop_gap`` metres behind it."""

    speed: float = 7.0
    lookahead: float = 5.0
    brake_for_lead: bool = False
    stop_gap: float = 2.5
    speed_gain: float = 1.5

    def __call__(self, env, info: dict) -> np.ndarray:
        ego, lim = info["ego"], env.config.limits
        x, y, yaw, v = ego["x"], ego["y"], ego["yaw"], ego["speed"]
        s = info["route"]["progress"]
        target = env.corridor.point_at(s + max(self.lookahead, 0.8 * v))
        dx, dy = target[0] - x, target[1] - y
        fx, fy = math.cos(yaw) * dx + math.sin(yaw) * dy, -math.sin(yaw) * dx + math.cos(yaw) * dy
        d2 = fx * fx + fy * fy
        steer = math.atan(lim.wheelbase * 2.0 * fy / d2) if d2 > 1e-6 else 0.0
        steer_rate = (steer - ego["steer"]) / env.dt
        accel = self.speed_gain * (self.speed - v)
        if self.brake_for_lead:
            gap = self.lead_gap(env, info)
            if gap is not None:
                room = gap - self.stop_gap
                need = v * v / (2.0 * room) if room > 0.05 else lim.max_brake
                if need > 0.3 or room < 0.5:
                    accel = min(accel, -need)
        return np.array([accel, steer_rate], dtype=np.float32)

    @staticmethod
    def lead_gap(env, info: dict, lateral_margin: float = 0.3, horizon: float = 40.0):
        """Metres of free road between the ego's front and the nearest actor box in its
        path ahead (boxes whose footprint comes within the ego's width), or None."""
        ego = info["ego"]
        c, s = math.cos(ego["yaw"]), math.sin(ego["yaw"])
        L, W = env.config.ego_size[0], env.config.ego_size[1]
        best = None
        for b in info["actors"]:
            pose, size = np.asarray(b["pose"]), np.asarray(b["size"])
            dx, dy = pose[0, 3] - ego["x"], pose[1, 3] - ego["y"]
            fx, fy = c * dx + s * dy, -s * dx + c * dy
            half = 0.5 * float(np.hypot(size[0], size[1]))
            if fx <= 0 or fx > horizon or abs(fy) > W / 2 + half * 0.6 + lateral_margin:
                continue
            gap = fx - L / 2 - size[0] / 2
            best = gap if best is None else min(best, gap)
        return best
