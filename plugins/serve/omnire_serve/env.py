"""A gymnasium environment: drive the ego through a reconstructed log (docs/closed_loop.md).

``reset(seed)`` puts the ego at the log's first recorded pose, moving at the recorded
speed; each ``step`` advances the scene by one log interval (``dt``, 0.1 s at 10 Hz): the
ego moves by the kinematic bicycle model (bicycle.py) under the action, the other actors
replay the log or follow the scenario's edits, and the cameras mounted on the ego's new pose
are rendered. Actions: ``"bicycle"`` = (acceleration m/s^2, steering rate rad/s);
``"waypoints"`` = K target points (x forward, y left) in the ego frame, one per future
step, followed by :func:`~omnire_serve.bicycle.track_waypoints`.

The episode ends (terminated) on a collision (the ego's footprint overlaps an actor's box at
the rendered moment), on leaving the drivable corridor (the ego's centre beyond the
corridor's border, corridor.py), or at the route's end (within ``end_tolerance`` metres of
it); it is truncated when the log has no later moment to show.

Observations: a dict camera name -> (H, W, 3) uint8; with ``EnvConfig.lidar`` also
``"lidar"`` -> (B, A) float32 range image (metres, 0 where the ray returned nothing) of one
revolution of the beam model (``EnvConfig.beam_model``, default the scene's) from the LiDAR
mounted on the ego as recorded at the log's first frame (omnire_serve.lidar). ``info``: ``t`` seconds, ``timestamp``
microseconds, ``ego`` (pose 4x4, x, y, yaw, speed, steer, accel), ``actors`` (boxes: id,
class, category, pose 4x4, size), ``route`` (progress s, length, lateral offset, corridor
widths), ``event`` (None, "collision", "off_corridor", "route_end", "log_end") and
``collided_with`` (the actor's box, on a collision).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from omnire_serve.bicycle import BicycleLimits, EgoState, advance, track_waypoints
from omnire_serve.boxes import footprint, footprint_of, overlap
from omnire_serve.corridor import Corridor
from omnire_serve.lidar import range_image

LIDAR_OBSERVATION = "lidar"
"""The observation key of the LiDAR range image."""


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """``cameras``: rendered cameras (default: all); ``size``: (width, height) of every
    observation image (default: the cameras' own); ``action``: "bicycle" or "waypoints"
    (``waypoints`` of them); ``ego_size``: the ego's (length, width, height) box, centred
    on the rig origin; ``end_tolerance``: metres before the route's end that count as
    reaching it; ``scenario``: the JSON tables of the edits every episode starts with;
    ``lidar``: add the LiDAR range image to the observations (off by default); ``beam_model``:
    its rays, as /render_lidar takes them (default: the scene's)."""

    cameras: Optional[tuple[str, ...]] = None
    size: Optional[tuple[int, int]] = None
    action: str = "bicycle"
    waypoints: int = 4
    limits: BicycleLimits = BicycleLimits()
    ego_size: tuple[float, float, float] = (4.8, 2.0, 1.8)
    end_tolerance: float = 1.0
    scenario: Optional[dict] = None
    lidar: bool = False
    beam_model: Optional[dict] = None


class DrivingEnv(gym.Env):
    """See the module docstring. ``transport``: a LocalTransport or HttpTransport."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, transport, config: EnvConfig = EnvConfig(), render_mode: Optional[str] = None) -> None:
        if config.action not in ("bicycle", "waypoints"):
            raise ValueError(f"EnvConfig.action {config.action!r}: expected 'bicycle' or 'waypoints'")
        self.transport, self.config, self.render_mode = transport, config, render_mode
        meta = transport.metadata()
        self.scene_meta = meta
        self.start_us = int(meta["time"]["start_us"])
        self.duration = float(meta["time"]["duration_s"])
        stamps = np.asarray(meta["time"]["frame_timestamps_us"], dtype=np.int64)
        self.log_seconds = (stamps - stamps[0]) / 1e6
        self.dt = float(np.median(np.diff(self.log_seconds))) if len(stamps) > 1 else 0.1
        self.rig = np.asarray(meta["ego"]["rig_to_world"], dtype=np.float64)
        self.corridor = Corridor.from_json(meta["route"])
        cams = {c["name"]: c for c in meta["cameras"]}
        self.cameras = tuple(config.cameras or cams)
        unknown = [c for c in self.cameras if c not in cams]
        if unknown:
            raise ValueError(f"EnvConfig.cameras {unknown}: not in the scene; cameras: {list(cams)}")
        observed = {name: spaces.Box(0, 255, (h, w, 3), np.uint8)
                    for name in self.cameras
                    for w, h in [config.size or (cams[name]["width"], cams[name]["height"])]}
        self.lidar_shape: Optional[tuple[int, int]] = None
        if config.lidar:
            observed[LIDAR_OBSERVATION] = self._lidar_space(meta)
        self.observation_space = spaces.Dict(observed)
        lim = config.limits
        if config.action == "bicycle":
            self.action_space = spaces.Box(np.array([-lim.max_brake, -lim.max_steer_rate], np.float32),
                                           np.array([lim.max_accel, lim.max_steer_rate], np.float32), dtype=np.float32)
        else:
            self.action_space = spaces.Box(-60.0, 60.0, (config.waypoints, 2), np.float32)
        self._yaw_rec = np.arctan2(self.rig[:, 1, 0], self.rig[:, 0, 0])
        self.state: Optional[EgoState] = None
        self.t = 0.0
        self.accel = 0.0
        self._last_obs = None

    def _lidar_space(self, meta: dict) -> spaces.Box:
        lidar = meta.get("lidar")
        if lidar is None:
            raise ValueError("EnvConfig.lidar: the scene recorded no LiDAR")
        if LIDAR_OBSERVATION in self.cameras:
            raise ValueError(f"EnvConfig.lidar: a camera is named {LIDAR_OBSERVATION!r}, the LiDAR observation's key")
        model = self.config.beam_model or lidar["beam_model"]
        if model is None:
            raise ValueError("EnvConfig.lidar: the scene has no LiDAR beam model; give EnvConfig.beam_model")
        self.sensor_to_rig = np.asarray(lidar["sensor_to_rig"], dtype=np.float64)
        self.lidar_shape = (len(model["elevations_deg"]), int(round(360.0 / model["azimuth_step_deg"])))
        self.max_range = float(model["max_range"])
        return spaces.Box(0.0, self.max_range, self.lidar_shape, np.float32)

    # ------------------------------------------------------------------ poses
    def rig_pose(self, state: EgoState) -> np.ndarray:
        """(4, 4) the rig at ``state``: its height, roll and pitch those of the nearest
        recorded rig pose, its heading the state's."""
        k = int(np.argmin(np.linalg.norm(self.rig[:, :2, 3] - [state.x, state.y], axis=1)))
        turn = state.yaw - self._yaw_rec[k]
        c, s = math.cos(turn), math.sin(turn)
        P = self.rig[k].copy()
        P[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ P[:3, :3]
        P[0, 3], P[1, 3] = state.x, state.y
        return P

    def timestamp(self, t: float) -> int:
        return self.start_us + int(round(t * 1e6))

    def _initial_state(self) -> EgoState:
        P = self.rig[0]
        speed = (float(np.linalg.norm(self.rig[1, :2, 3] - P[:2, 3]) / (self.log_seconds[1] - self.log_seconds[0]))
                 if len(self.rig) > 1 else 0.0)
        return EgoState(float(P[0, 3]), float(P[1, 3]), float(self._yaw_rec[0]), speed, 0.0)

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        scenario = (options or {}).get("scenario", self.config.scenario)
        self.transport.reset(scenario)
        self.state, self.t, self.accel = self._initial_state(), 0.0, 0.0
        obs, boxes = self._observe()
        return obs, self._info(boxes, None, None)

    def step(self, action):
        if self.state is None:
            raise RuntimeError("DrivingEnv.step before reset")
        act = np.asarray(action, dtype=np.float64)
        if act.shape != self.action_space.shape or not np.isfinite(act).all():
            raise ValueError(f"action {action!r}: expected finite values of shape {self.action_space.shape}")
        if self.config.action == "bicycle":
            accel, steer_rate = float(act[0]), float(act[1])
        else:
            accel, steer_rate = track_waypoints(self.state, act, self.dt, self.config.limits)
        before = self.state
        self.state = advance(before, accel, steer_rate, self.dt, self.config.limits)
        self.accel = (self.state.speed - before.speed) / self.dt
        s_before = self.corridor.project([before.x, before.y])[0]
        t_next = self.t + self.dt
        truncated = t_next > self.duration + 1e-6
        self.t = min(t_next, self.duration)
        obs, boxes = self._observe()
        s, lateral = self.corridor.project([self.state.x, self.state.y])
        left, right = self.corridor.width_at(s)
        hit = self.collision(boxes)
        event = None
        if hit is not None:
            event = "collision"
        elif lateral > left or -lateral > right:
            event = "off_corridor"
        elif s >= self.corridor.length - self.config.end_tolerance:
            event = "route_end"
        elif truncated:
            event = "log_end"
        terminated = event in ("collision", "off_corridor", "route_end")
        reward = float(s - s_before) - (10.0 if event == "collision" else 0.0) - (5.0 if event == "off_corridor"
                                                                                 else 0.0)
        return obs, reward, terminated, bool(truncated and not terminated), self._info(boxes, event, hit)

    def render(self):
        if self.render_mode == "rgb_array" and self._last_obs is not None:
            return np.concatenate([self._last_obs[n] for n in self.cameras], axis=1)
        return None

    # ------------------------------------------------------------------ helpers
    def _observe(self) -> tuple[dict, list[dict]]:
        stamp = self.timestamp(self.t)
        images = self.transport.render_rig(self.rig_pose(self.state), stamp, list(self.cameras), self.config.size)
        obs = {n: np.ascontiguousarray(images[n], dtype=np.uint8) for n in self.cameras}
        if self.lidar_shape is not None:
            sensor = self.rig_pose(self.state) @ self.sensor_to_rig
            _, points = self.transport.render_lidar(sensor, stamp, self.config.beam_model)
            obs[LIDAR_OBSERVATION] = range_image(points, sensor, self.lidar_shape, self.max_range)
        self._last_obs = obs
        return obs, self.transport.actors_at(stamp)

    def ego_footprint(self, state: Optional[EgoState] = None) -> np.ndarray:
        st = state or self.state
        return footprint([st.x, st.y], st.yaw, self.config.ego_size[0], self.config.ego_size[1])

    def collision(self, boxes: list[dict]) -> Optional[dict]:
        """The first actor box the ego's footprint overlaps, or None."""
        ego = self.ego_footprint()
        for b in boxes:
            pose, size = np.asarray(b["pose"]), np.asarray(b["size"])
            if np.linalg.norm(pose[:2, 3] - ego.mean(0)) > 0.5 * (np.hypot(*size[:2]) + np.hypot(*self.config.ego_size[:2])):
                continue  # too far to touch
            if overlap(ego, footprint_of(pose, size)):
                return b
        return None

    def _info(self, boxes: list[dict], event: Optional[str], hit: Optional[dict]) -> dict:
        st = self.state
        s, lateral = self.corridor.project([st.x, st.y])
        left, right = self.corridor.width_at(s)
        return {"t": self.t, "timestamp": self.timestamp(self.t),
                "ego": {"pose": self.rig_pose(st), "x": st.x, "y": st.y, "yaw": st.yaw, "speed": st.speed,
                        "steer": st.steer, "accel": self.accel},
                "actors": boxes,
                "route": {"progress": s, "length": self.corridor.length, "lateral": lateral, "left": left,
                          "right": right},
                "event": event, "collided_with": hit}
