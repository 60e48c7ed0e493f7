"""Reference drivers for the environment (examples and tests): a lane keeper that follows
the route by pure pursuit at a set speed, optionally braking for the actor ahead."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from omnire_serve.boxes import gap_ahead


@dataclasses.dataclass
class LaneKeeper:
    """Bicycle actions (acceleration, steering rate) for a :class:`~omnire_serve.env.DrivingEnv`:
    steer towards the route point ``lookahead`` metres (at least; more when fast) ahead of
    the ego's projection; hold ``speed`` m/s. ``brake_for_lead``: also brake for an actor box
    in the ego's path ahead, to stop ``stop_gap`` metres behind it: once stopping within the
    room left takes ``comfort_brake`` m/s^2 or more, it brakes as hard as that takes."""

    speed: float = 7.0
    lookahead: float = 5.0
    brake_for_lead: bool = False
    stop_gap: float = 2.5
    speed_gain: float = 1.5
    comfort_brake: float = 3.0
    _seen: dict = dataclasses.field(default_factory=dict, repr=False)  # actor id -> (t, xy) at its last sighting

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
            found = self.lead_gap(env, info)
            if found is not None:
                gap, lead = found
                v_lead = self._lead_speed(lead, info)
                # the room to stop in: the gap left, plus what the lead needs to stop at the same braking
                room = gap - self.stop_gap + v_lead * v_lead / (2.0 * self.comfort_brake)
                need = v * v / (2.0 * room) if room > 0.05 else lim.max_brake  # to stop within the room
                if need >= self.comfort_brake or room <= 0.05:
                    accel = -min(need, lim.max_brake)
        return np.array([accel, steer_rate], dtype=np.float32)

    def _lead_speed(self, lead: dict, info: dict) -> float:
        """The lead actor's speed along the ego's heading, from its position at the previous
        step (0 at its first sighting); remembered per actor, forgotten at a new episode."""
        if info["t"] <= 0.0:
            self._seen = {}
        pose = np.asarray(lead["pose"])
        prev = self._seen.get(lead["id"])
        self._seen[lead["id"]] = (info["t"], pose[:2, 3].copy())
        if prev is None or info["t"] <= prev[0]:
            return 0.0
        yaw = info["ego"]["yaw"]
        d = (pose[:2, 3] - prev[1]) / (info["t"] - prev[0])
        return max(0.0, float(d[0] * math.cos(yaw) + d[1] * math.sin(yaw)))

    @staticmethod
    def lead_gap(env, info: dict, lateral_margin: float = 0.3, horizon: float = 40.0):
        """(metres of free road between the ego's front and the nearest actor box in its
        path ahead (boxes whose footprint reaches into the ego's width plus ``lateral_margin``
        on the ground plane), that actor's box),
        or None."""
        ego = info["ego"]
        L, W = env.config.ego_size[0], env.config.ego_size[1]
        best = None
        for b in info["actors"]:
            gap = gap_ahead((ego["x"], ego["y"]), ego["yaw"], L, W, np.asarray(b["pose"]), np.asarray(b["size"]),
                            lateral_margin, horizon)
            if gap is None:
                continue
            if best is None or gap < best[0]:
                best = (gap, b)
        return best
