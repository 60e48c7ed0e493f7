"""The ego's motion: a kinematic bicycle model driven by acceleration and steering rate.

State: position (x, y) of the reference point (the rig origin) on the ground plane, heading
``yaw`` (radians, world z up), ``speed`` (m/s, >= 0: the ego does not reverse) and front
wheel angle ``steer`` (radians). Rates: x' = v cos(yaw), y' = v sin(yaw),
yaw' = v tan(steer) / wheelbase, v' = a, steer' = steering rate; integrated with the
midpoint rule over ``substeps`` sub-steps per step.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class BicycleLimits:
    """The vehicle: ``wheelbase`` metres; accelerations m/s^2 (``max_brake`` > 0 is the
    strongest deceleration); ``max_steer`` radians; ``max_steer_rate`` radians/s;
    ``max_speed`` m/s."""

    wheelbase: float = 3.0
    max_accel: float = 4.0
    max_brake: float = 8.0
    max_steer: float = 0.6
    max_steer_rate: float = 1.0
    max_speed: float = 25.0


@dataclasses.dataclass(frozen=True)
class EgoState:
    x: float
    y: float
    yaw: float
    speed: float
    steer: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw, self.speed, self.steer])


def _rates(s: np.ndarray, accel: float, steer_rate: float, wheelbase: float) -> np.ndarray:
    x, y, yaw, v, d = s
    return np.array([v * math.cos(yaw), v * math.sin(yaw), v * math.tan(d) / wheelbase, accel, steer_rate])


def advance(state: EgoState, accel: float, steer_rate: float, dt: float, limits: BicycleLimits = BicycleLimits(),
            substeps: int = 10) -> EgoState:
    """The state ``dt`` seconds later under constant ``accel`` (m/s^2) and ``steer_rate``
    (rad/s), both clipped to ``limits``; speed is kept in [0, max_speed] and the steering
    angle in [-max_steer, max_steer] (their rates are zero while held at a bound)."""
    if not (math.isfinite(accel) and math.isfinite(steer_rate) and dt > 0):
        raise ValueError(f"advance: accel {accel}, steer_rate {steer_rate} must be finite and dt {dt} > 0")
    a = min(max(accel, -limits.max_brake), limits.max_accel)
    w = min(max(steer_rate, -limits.max_steer_rate), limits.max_steer_rate)
    s = state.as_array().astype(np.float64)
    h = dt / substeps
    for _ in range(substeps):
        a_eff = 0.0 if (s[3] <= 0.0 and a < 0) or (s[3] >= limits.max_speed and a > 0) else a
        w_eff = 0.0 if abs(s[4]) >= limits.max_steer and w * s[4] > 0 else w
        # braking to a stop inside the sub-step: move only until the stop (v / |a| seconds)
        moving = min(h, s[3] / -a_eff) if a_eff < 0 else h
        mid = s + 0.5 * moving * _rates(s, a_eff, w_eff, limits.wheelbase)
        s = s + moving * _rates(mid, a_eff, w_eff, limits.wheelbase)
        s[4] += (h - moving) * w_eff
        s[3] = min(max(s[3], 0.0), limits.max_speed)
        s[4] = min(max(s[4], -limits.max_steer), limits.max_steer)
    return EgoState(float(s[0]), float(s[1]), float(math.atan2(math.sin(s[2]), math.cos(s[2]))), float(s[3]),
                    float(s[4]))


def track_waypoints(state: EgoState, waypoints: np.ndarray, dt: float,
                    limits: BicycleLimits = BicycleLimits()) -> tuple[float, float]:
    """(accel, steer_rate) that follow ``waypoints`` (K, 2), metres in the ego frame (x
    forward, y left), the k-th to be reached ``(k + 1) * dt`` seconds from now: the speed
    aims at the first waypoint's distance per step, the steering at the pure-pursuit angle
    towards the last waypoint (curvature 2 y / (x^2 + y^2))."""
    wp = np.asarray(waypoints, dtype=np.float64)
    target_speed = float(np.linalg.norm(wp[0])) / dt
    x, y = wp[-1]
    d2 = x * x + y * y
    curvature = 2.0 * y / d2 if d2 > 1e-6 else 0.0
    target_steer = math.atan(limits.wheelbase * curvature)
    return (target_speed - state.speed) / dt, (target_steer - state.steer) / dt
