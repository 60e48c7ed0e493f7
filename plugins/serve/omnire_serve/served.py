"""The scene a server holds (:class:`ServedScene`: one Reconstruction, its cameras, time
span, extent, actors, route and corridor) and the state one client drives in it
(:class:`Episode`: the scenario's edits plus actor trajectories sent by the client).

Times at this boundary are integer microseconds on the log's clock (the dataset's
timestamps, as neurad-studio's API has them) or seconds since the log's first frame inside.
Poses are 4x4 in the scene's world frame: cameras OpenCV camera-to-world (x right, y down,
z forward), the rig (ego) x forward, y left, z up, actor boxes x along the heading, y left,
z up (centre of the box). Sizes are (length, width, height) metres.

Concurrency: every episode has a lock for its state; renders of all episodes share one lock
(one render at a time: the renderer uses every core anyway). Simulation objects are never
changed once built: a change builds a new one, so a render in flight keeps a consistent view.
"""
from __future__ import annotations

import dataclasses
import math
import threading
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from omnire.api import BeamModel, Camera, Reconstruction, UserError, sensor_path
from omnire.command_api import rig_poses
from omnire_serve.checks import Limits, image_size, pose_matrix
from omnire_serve.corridor import Corridor, build_corridor
from omnire_serve.errors import RequestError
from omnire_serve.imaging import to_uint8
from omnire_serve.lidar import SweepPoints, beam_model_from, beam_model_json, render_points
from omnire_serve.tables import field_of_error, parse_tables
from omnire_sim import ActorEdit, Scenario, Simulation, Trajectory, Waypoint
from omnire_sim.edits import Where

EGO_SHADOW = np.array([6.0, 2.6, 4.0])
"""(length, width, height) metres around the rig whose LiDAR points are the ego car's own."""
MAX_TRAJECTORY = 100_000
"""Most poses one actor trajectory may hold."""


@dataclasses.dataclass(frozen=True)
class Box:
    """An actor's box at one moment: ``pose`` (4, 4) box-to-world, ``size`` (3,) metres."""

    id: str
    class_name: str
    category: str
    pose: np.ndarray
    size: np.ndarray

    def as_json(self) -> dict:
        return {"id": self.id, "class": self.class_name, "category": self.category,
                "pose": np.round(self.pose, 6).tolist(), "size": np.round(self.size, 4).tolist()}


class ServedScene:
    """One trained scene served to clients. ``scenario``: the edits every episode starts
    from (and returns to on reset); ``assets``: the directory asset runs and motion files
    of client scenarios must lie in (None: clients may not insert actors of other runs)."""

    def __init__(self, recon: Reconstruction, plugins, scenario: Optional[Scenario] = None,
                 limits: Limits = Limits(), assets: Optional[Path] = None) -> None:
        self.recon, self.plugins, self.limits = recon, plugins, limits
        self.assets = None if assets is None else Path(assets).resolve()
        self.base = scenario if scenario is not None else Scenario()
        scene = recon.scene
        ts = np.asarray(scene.frame_timestamps, dtype=np.float64)
        self.frame_us = np.round(ts * 1e6).astype(np.int64)
        self.start_us, self.end_us = int(self.frame_us[0]), int(self.frame_us[-1])
        self.seconds = ts - ts[0]
        self.rig = rig_poses(scene)
        self.camera_names = [c.name for c in scene.cameras]
        # the scene's extent: every recorded camera and ego position, actor box centre and LiDAR point
        where = [np.asarray(c.cam_to_world)[:, :3, 3] for c in scene.cameras] + [self.rig[:, :3, 3]]
        where += [np.asarray(t.poses)[np.asarray(t.present, bool), :3, 3] for t in scene.tracks]
        if scene.lidar is not None:
            where += [np.stack([p.min(0), p.max(0)]) for p in scene.lidar.points if p is not None and len(p)]
        allc = np.concatenate(where).astype(np.float64)
        self.extent = (allc.min(0), allc.max(0))
        self.tracks = {t.track_id: t for t in scene.tracks}
        self.actor_ids = [t for node in recon.actor_nodes().values() for t in node.track_ids]
        self.render_lock = threading.Lock()
        self._base_sim = Simulation(recon, self.base, plugins)
        self._corridor: Optional[Corridor] = None

    # ------------------------------------------------------------------ checks
    def seconds_at(self, t_us, field: str = "timestamp") -> float:
        """Seconds since the log's first frame of a timestamp in microseconds, which must
        lie inside the log."""
        if isinstance(t_us, bool) or not isinstance(t_us, int):
            raise RequestError(field, f"{t_us!r}: expected an integer timestamp in microseconds")
        if not self.start_us - 1 <= t_us <= self.end_us + 1:
            raise RequestError(field, f"{t_us} us is outside the log ({self.start_us} .. {self.end_us} us, "
                                      f"{self.seconds[-1]:.3f} s)")
        return min(max((t_us - self.start_us) / 1e6, 0.0), float(self.seconds[-1]))

    def camera_index(self, name, field: str = "camera_name") -> int:
        """Index of camera ``name`` (neurad-style ``CAM_`` prefixes are accepted)."""
        if not isinstance(name, str):
            raise RequestError(field, f"{name!r}: expected a camera name")
        for candidate in (name, name.removeprefix("CAM_")):
            if candidate in self.camera_names:
                return self.camera_names.index(candidate)
        raise RequestError(field, f"unknown camera {name!r}; cameras: {self.camera_names}")

    def pose(self, value, field: str) -> np.ndarray:
        return pose_matrix(value, field, self.extent, self.limits.margin)

    # ------------------------------------------------------------------ cameras
    def camera(self, c: int, cam_to_world: np.ndarray, size: Optional[tuple[int, int]] = None) -> Camera:
        """Camera ``c``'s lens (K scaled to ``size``) at ``cam_to_world`` (4, 4)."""
        cam = self.recon.scene.cameras[c]
        K = np.asarray(cam.intrinsics, dtype=np.float64).copy()
        w, h = size or (cam.width, cam.height)
        K[0] *= w / cam.width
        K[1] *= h / cam.height
        return Camera.from_numpy(K, cam_to_world, w, h, cam.name, self.recon.device)

    def mounted(self, c: int, rig_to_world: np.ndarray, seconds: float) -> np.ndarray:
        """(4, 4) camera ``c``'s pose on a rig at ``rig_to_world``: mounted as recorded at
        the frame nearest to ``seconds`` (as omnire sim mounts cameras on a file path)."""
        frame = float(np.interp(seconds, self.seconds, np.arange(len(self.seconds))))
        near = int(np.clip(np.round(frame), 0, len(self.seconds) - 1))
        c2w = np.asarray(self.recon.scene.cameras[c].cam_to_world, dtype=np.float64)
        return rig_to_world @ (np.linalg.inv(self.rig[near]) @ c2w[near])

    # ------------------------------------------------------------------ LiDAR
    @property
    def has_lidar_sensor(self) -> bool:
        """The scene recorded LiDAR (so a LiDAR pose on the rig is known)."""
        return self.recon.scene.lidar is not None

    def lidar_mounted(self, rig_to_world: np.ndarray, seconds: float) -> np.ndarray:
        """(4, 4) the LiDAR's pose on a rig at ``rig_to_world``: mounted as recorded at the
        frame nearest to ``seconds`` (as :meth:`mounted` mounts cameras)."""
        frame = float(np.interp(seconds, self.seconds, np.arange(len(self.seconds))))
        near = int(np.clip(np.round(frame), 0, len(self.seconds) - 1))
        sensor = sensor_path(self.recon.scene).at(float(self.recon.scene.frame_timestamps[near]))[0]
        return rig_to_world @ (np.linalg.inv(self.rig[near]) @ sensor)

    def beam_model(self, value, field: str = "beam_model") -> BeamModel:
        """A request's beam model (omnire_serve.lidar.beam_model_from), the scene's own by default."""
        if "lidar" not in self.recon.model.capabilities:
            raise RequestError("", f"the run's rasterizer {self.recon.model.rasterizer.name!r} cannot render LiDAR "
                                   "(no 'lidar' capability; omnire plugins lists the ones that can)", 409)
        lidar = self.recon.scene.lidar
        default = lidar.beam_model if lidar is not None else None
        return beam_model_from(value, default, self.limits.max_lidar_rays, field)

    def lidar_features(self) -> list[str]:
        return ["range", "intensity", "ray_drop"] if self.recon.model.lidar_features is not None else ["range"]

    def size_of(self, width, height, c: int, field: str = "") -> tuple[int, int]:
        cam = self.recon.scene.cameras[c]
        return image_size(width, height, (cam.width, cam.height), self.limits, field)

    # ------------------------------------------------------------------ scene facts
    @property
    def corridor(self) -> Corridor:
        """The route and drivable corridor (corridor.py), computed on first use."""
        if self._corridor is None:
            scene = self.recon.scene
            sweeps = scene.lidar.points if scene.lidar is not None else [None] * scene.num_frames
            # the actors' points and the ego car's own returns (a box around the rig) are not the corridor's borders
            boxes = [[(t.poses[f], t.size) for t in scene.tracks if t.present[f]] + [(self.rig[f], EGO_SHADOW)]
                     for f in range(scene.num_frames)]
            self._corridor = build_corridor(self.rig, sweeps, boxes)
        return self._corridor

    def metadata(self) -> dict:
        scene = self.recon.scene
        cams = []
        for c, cam in enumerate(scene.cameras):
            mount = np.linalg.inv(self.rig[0]) @ np.asarray(cam.cam_to_world, dtype=np.float64)[0]
            cams.append({"name": cam.name, "width": cam.width, "height": cam.height,
                         "intrinsics": np.round(np.asarray(cam.intrinsics, dtype=np.float64), 6).tolist(),
                         "camera_to_rig": np.round(mount, 6).tolist()})
        actors = []
        for tid in self.actor_ids:
            t = self.tracks[tid]
            actors.append({"id": tid, "class": t.class_name, "category": t.category,
                           "size": np.round(np.asarray(t.size, dtype=np.float64), 4).tolist(),
                           "stationary": bool(t.stationary)})
        return {
            "scene": scene.name, "attribution": scene.attribution,
            "time": {"start_us": self.start_us, "end_us": self.end_us, "duration_s": float(self.seconds[-1]),
                     "frame_timestamps_us": self.frame_us.tolist()},
            "cameras": cams,
            "extent": {"low": np.round(self.extent[0], 3).tolist(), "high": np.round(self.extent[1], 3).tolist(),
                       "margin": self.limits.margin},
            "limits": dataclasses.asdict(self.limits),
            "ego": {"rig_to_world": np.round(self.rig, 6).tolist()},
            "route": self.corridor.as_json(),
            "actors": actors,
            "lidar": self._lidar_metadata(),
        }

    def _lidar_metadata(self) -> Optional[dict]:
        """The scene's LiDAR: its mount on the rig (first frame), its beam model (None when
        the scene has none: /render_lidar then needs one) and the fields a sweep carries."""
        scene = self.recon.scene
        if scene.lidar is None:
            return None
        model = scene.lidar.beam_model
        return {"sensor_to_rig": np.round(self.lidar_mounted(np.eye(4), 0.0), 6).tolist(),
                "beam_model": None if model is None else beam_model_json(model),
                "features": self.lidar_features()}

    # ------------------------------------------------------------------ simulations
    def simulation(self, scenario: Scenario) -> Simulation:
        """A Simulation of ``scenario`` (the shared one for the base scenario)."""
        if scenario is self.base:
            return self._base_sim
        self.check_paths(scenario)
        try:
            return Simulation(self.recon, scenario, self.plugins)
        except UserError as exc:
            raise RequestError(field_of_error(str(exc)), str(exc)) from None

    def check_paths(self, scenario: Scenario) -> None:
        """Files a client's scenario names (asset runs, motion files) must lie in the assets
        directory: a client may not make the server read anything else."""
        paths = [(f"insert.{i}.run", ins.run) for i, ins in enumerate(scenario.inserts)]
        paths += [(f"insert.{i}.motion", ins.motion.file) for i, ins in enumerate(scenario.inserts)
                  if ins.motion is not None and ins.motion.file is not None]
        paths += [(f"actor.{i}.motion", a.motion.file) for i, a in enumerate(scenario.actors)
                  if a.motion is not None and a.motion.file is not None]
        for field, p in paths:
            if self.assets is None:
                raise RequestError(field, "this server reads no files for clients (start omnire serve with "
                                          "--assets DIR to allow asset runs and motion files inside DIR)", 403)
            full = scenario.resolve_path(p).resolve()
            if not full.is_relative_to(self.assets):
                raise RequestError(field, f"{p}: outside the assets directory {self.assets}", 403)

    def render_lidar(self, sim: Simulation, sensor_to_world: np.ndarray, seconds: float, model: BeamModel
                     ) -> SweepPoints:
        """One revolution of ``model`` of ``sim`` from ``sensor_to_world`` (4, 4) at
        ``seconds`` (omnire_serve.lidar.render_points)."""
        t0 = float(self.recon.scene.frame_timestamps[0])
        stamp = self.start_us + int(round(seconds * 1e6))
        with self.render_lock, torch.no_grad():
            return render_points(self.recon, sensor_to_world, sim.time(seconds), t0 + seconds, model, sim, stamp)

    def render(self, sim: Simulation, camera: Camera, seconds: float) -> np.ndarray:
        """(H, W, 3) uint8 image of ``sim`` through ``camera`` at ``seconds``."""
        with self.render_lock, torch.no_grad():
            return to_uint8(sim.render(camera, sim.time(seconds)).rgb)

    def render_many(self, sim: Simulation, cameras: list[Camera], seconds: float) -> list[np.ndarray]:
        """(H, W, 3) uint8 images of ``sim`` through each of ``cameras`` at ``seconds`` (a rig;
        side by side where that is faster: ``Reconstruction.render_cameras``)."""
        with self.render_lock, torch.no_grad():
            return [to_uint8(r.rgb) for r in sim.render_cameras(cameras, sim.time(seconds))]


class Episode:
    """One client's state in a :class:`ServedScene`: the scenario's edits (``scenario``)
    and the actor trajectories the client set (``overrides``: track id -> trajectory, or
    None for an actor the client removed)."""

    def __init__(self, served: ServedScene) -> None:
        self.served = served
        self.lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        """Back to the recorded state with the server's scenario."""
        with self.lock:
            self.scenario = self.served.base
            self.overrides: dict[str, Optional[Trajectory]] = {}
            self.sim = self.served.simulation(self.scenario)
            self._trajectories: Optional[list[dict]] = None

    def _rebuild(self, scenario: Scenario, overrides: dict) -> None:
        edits = [e for e in scenario.actors if e.track not in overrides]
        for track, traj in overrides.items():
            where = Where("update_actors", f"actor {track}")
            edits.append(ActorEdit(track, remove=True, where=where) if traj is None
                         else ActorEdit(track, trajectory=traj, where=where))
        for i, ins in enumerate(scenario.inserts):
            if ins.replace is not None and ins.replace in overrides:
                raise RequestError("uuid", f"actor {ins.replace} is replaced by insert {ins.id!r} of the scenario; "
                                           "its trajectory cannot be set too")
        combined = dataclasses.replace(scenario, actors=tuple(edits))
        if overrides:
            combined = combined.check()
        sim = self.served.simulation(combined if overrides else scenario)
        self.scenario, self.overrides, self.sim, self._trajectories = scenario, overrides, sim, None

    def set_scenario(self, tables) -> None:
        """Replace the edits by the JSON tables (see tables.py); actor trajectories set by
        update_actors are kept on top. Nothing changes when the tables are refused."""
        base_dir = self.served.assets or Path.cwd()
        scenario = parse_tables(tables, base_dir)
        with self.lock:
            self._rebuild(scenario, dict(self.overrides))

    # ------------------------------------------------------------------ actors
    def boxes_at(self, seconds: float) -> list[Box]:
        """The boxes of every actor drawn at ``seconds`` (edits applied)."""
        sim, served = self.sim, self.served
        recon = served.recon
        time = sim.time(seconds)
        edited = {(a.node_name, a.instance) for a in sim.actors if not a.inserted}
        out = []
        with torch.no_grad():
            for name, node in recon.actor_nodes().items():
                state = node.state_at(time)
                for k, i in enumerate(state.ids.tolist()):
                    if (name, i) in edited:
                        continue
                    out.append(self._box(node.track_ids[i], recon, state.R[k], state.t[k]))
            for a in sim.actors:
                if a.removed:
                    continue
                got = a.state(seconds)
                if got is None:
                    continue
                st = got[0]
                box = self._box(a.node.track_ids[a.instance], a.owner, st.R[0], st.t[0])
                out.append(dataclasses.replace(box, id=a.key) if a.inserted else box)
        return out

    @staticmethod
    def _box(track: str, owner: Reconstruction, R: torch.Tensor, t: torch.Tensor) -> Box:
        info = next(x for x in owner.scene.tracks if x.track_id == track)
        P = np.eye(4)
        P[:3, :3] = R.detach().cpu().double().numpy()
        P[:3, 3] = t.detach().cpu().double().numpy()
        return Box(track, info.class_name, info.category, P, np.asarray(info.size, dtype=np.float64))

    def trajectories(self) -> list[dict]:
        """Every drawn actor's trajectory over the log's frames, neurad-studio's shape:
        ``uuid``, ``poses`` (N, 4, 4), ``timestamps`` (N,) microseconds, ``dims`` (3,)."""
        with self.lock:
            if self._trajectories is not None:
                return self._trajectories
            per: dict[str, dict] = {}
            for f, sec in enumerate(self.served.seconds):
                for box in self.boxes_at(float(sec)):
                    item = per.setdefault(box.id, {"uuid": box.id, "poses": [], "timestamps": [],
                                                   "dims": np.round(box.size, 4).tolist()})
                    item["poses"].append(np.round(box.pose, 6).tolist())
                    item["timestamps"].append(int(self.served.frame_us[f]))
            self._trajectories = list(per.values())
            return self._trajectories

    def update_actors(self, items) -> None:
        """neurad-studio's update: the actors listed follow the given poses (box yaw and
        position; roll and pitch are dropped, as scenario trajectories have none), actors
        not listed are removed, actors listed with their current poses stay as drawn; actors
        inserted by the scenario (from other runs) keep following it."""
        served = self.served
        if not isinstance(items, list):
            raise RequestError("", "expected a JSON list of actor trajectories")
        current = {t["uuid"]: t for t in self.trajectories()}
        inserted = {a.key for a in self.sim.actors if a.inserted}
        overrides: dict[str, Optional[Trajectory]] = {}
        seen = set()
        for i, item in enumerate(items):
            if not isinstance(item, dict):
                raise RequestError(f"{i}", "expected an object with uuid, poses, timestamps, dims")
            for key in ("uuid", "poses", "timestamps", "dims"):
                if key not in item:
                    raise RequestError(f"{i}.{key}", "missing")
            uuid = item["uuid"]
            if isinstance(uuid, str) and uuid in inserted:
                continue  # an actor of another run: it follows the scenario's insertion
            if not isinstance(uuid, str) or uuid not in served.actor_ids:
                raise RequestError(f"{i}.uuid", f"{uuid!r}: not an actor of this scene (GET /get_actors lists them)")
            if uuid in seen:
                raise RequestError(f"{i}.uuid", f"{uuid}: listed twice")
            seen.add(uuid)
            poses, stamps = item["poses"], item["timestamps"]
            if not isinstance(poses, list) or not isinstance(stamps, list) or len(poses) != len(stamps):
                raise RequestError(f"{i}.poses", "poses and timestamps must be lists of the same length")
            if not 1 <= len(poses) <= MAX_TRAJECTORY:
                raise RequestError(f"{i}.poses", f"{len(poses)} poses: expected 1 .. {MAX_TRAJECTORY}")
            dims = item["dims"]
            if (not isinstance(dims, list) or len(dims) != 3
                    or not all(isinstance(d, (int, float)) and math.isfinite(d) for d in dims)):
                raise RequestError(f"{i}.dims", "expected 3 finite numbers (the actor's size)")
            P = np.stack([served.pose(p, f"{i}.poses.{k}") for k, p in enumerate(poses)])
            sec = np.array([served.seconds_at(t, f"{i}.timestamps.{k}") for k, t in enumerate(stamps)])
            if len(sec) > 1 and not np.all(np.diff(sec) > 0):
                raise RequestError(f"{i}.timestamps", "timestamps must increase strictly")
            old = current.get(uuid)
            if (old is not None and old["timestamps"] == list(stamps)
                    and np.abs(np.asarray(old["poses"]) - P).max() < 1e-4):
                if uuid in self.overrides:
                    overrides[uuid] = self.overrides[uuid]
                continue  # unchanged: drawn as before
            yaw = np.degrees(np.arctan2(P[:, 1, 0], P[:, 0, 0]))
            overrides[uuid] = Trajectory(tuple(Waypoint(float(p[0, 3]), float(p[1, 3]), float(s), float(p[2, 3]),
                                                        float(y)) for p, s, y in zip(P, sec, yaw)))
        for uuid in current:
            if uuid not in seen and uuid in served.actor_ids:
                overrides[uuid] = None
        with self.lock:
            self._rebuild(self.scenario, overrides)

    # ------------------------------------------------------------------ rendering
    def render_camera(self, c: int, cam_to_world: np.ndarray, seconds: float,
                      size: Optional[tuple[int, int]] = None) -> np.ndarray:
        sim = self.sim
        return self.served.render(sim, self.served.camera(c, cam_to_world, size), seconds)

    def render_lidar(self, sensor_to_world: np.ndarray, seconds: float, model: BeamModel) -> SweepPoints:
        """The LiDAR at ``sensor_to_world`` (4, 4) with this episode's edits."""
        return self.served.render_lidar(self.sim, sensor_to_world, seconds, model)

    def render_rig(self, rig_to_world: np.ndarray, seconds: float, cameras: list[int],
                   sizes: list[tuple[int, int]]) -> dict[str, np.ndarray]:
        """Cameras ``cameras`` (indices) mounted on the rig, each at its size in ``sizes``."""
        sim, served = self.sim, self.served
        lenses = [served.camera(c, served.mounted(c, rig_to_world, seconds), size) for c, size in zip(cameras, sizes)]
        return dict(zip([served.camera_names[c] for c in cameras], served.render_many(sim, lenses, seconds)))
