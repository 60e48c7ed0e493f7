"""The scene as the viewer shows it, without any web machinery: one object per non-actor
node and per actor, each in its own frame with a world pose; actor boxes for picking;
dataset cameras; and the server render of any camera with the real rasterizer.

Everything drawn is a simulated scene (:class:`omnire_sim.Simulation`: a scenario file's
edits, if any, and the panel's hide / move edits, see :mod:`omnire_viewer.edits`). Actors are
drawn by their node at the identity pose (their box frame at the moment: posed and skinned
for pedestrians, deformed for deformable actors) and placed by the box pose the simulation
gives them, so moving a rigid actor only moves its object; objects whose Gaussians change
(pedestrians re-skinned for a new frame or gait) are rebuilt.
"""
from __future__ import annotations

import dataclasses
import math
import threading
from typing import Optional

import numpy as np
import torch

from omnire.api import (
    ActorNode,
    ActorState,
    Camera,
    Drawn,
    EnvironmentNode,
    Gaussians,
    SceneTime,
    rotmat_to_quat,
    sensor_path,
)
from omnire_sim import Scenario, Simulation
from omnire_sim.cli import sim_sweep
from omnire_viewer.edits import ActorEdit, EditModel, drawn_actors
from omnire_viewer.splats import SplatArrays, sky_splats, splat_arrays

KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")


@dataclasses.dataclass(frozen=True)
class ActorInfo:
    """One actor the viewer can select."""

    track_id: str
    class_name: str
    category: str
    node: str
    instance: int
    size: tuple[float, float, float]
    frames: tuple[int, int]
    """First and last frame it is present (in its own run's log)."""
    inserted_from: Optional[str] = None
    """An actor the scenario inserts (``track_id`` is then its insert id): its track id in
    the run it comes from."""

    @property
    def inserted(self) -> bool:
        return self.inserted_from is not None

    def describe(self) -> str:
        box = f"box {self.size[0]:.1f} x {self.size[1]:.1f} x {self.size[2]:.1f} m"
        if self.inserted:
            return (f"**{self.track_id}** (inserted by the scenario: track {self.inserted_from} of another run, "
                    f"its `{self.node}` node): {self.class_name} ({self.category}), {box}")
        return (f"**{self.track_id}**: {self.class_name} ({self.category}), node `{self.node}`, {box}, "
                f"frames {self.frames[0]}-{self.frames[1]}")


@dataclasses.dataclass
class SceneObject:
    """A set of splats with a world pose (box-to-world for actors, identity otherwise).

    ``version`` changes whenever ``splats`` do (the app re-sends the object then)."""

    name: str
    node: Optional[str]
    """The node toggle it follows (None: an inserted actor, which belongs to no node here)."""
    track_id: Optional[str]
    splats: SplatArrays
    position: np.ndarray
    wxyz: np.ndarray
    version: int


@dataclasses.dataclass
class _Cached:
    tensors: tuple
    versions: tuple
    splats: SplatArrays
    version: int


def camera_from_view(position, wxyz, fov: float, width: int, height: int, device="cpu") -> Camera:
    """A pinhole :class:`Camera` from a browser view: position (3,), wxyz (4,) camera-to-world
    rotation in OpenCV axes, vertical field of view ``fov`` (radians), image size."""
    from omnire.api import quat_to_rotmat

    R = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz, np.float64)))
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = R
    c2w[:3, 3] = torch.as_tensor(np.asarray(position, np.float64))
    f = 0.5 * height / math.tan(0.5 * fov)
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return Camera(K.float().to(device), c2w.float().to(device), int(width), int(height))


class ViewerScene:
    """The viewer's model of a :class:`~omnire.runtime.Reconstruction`, as a simulation.

    What is drawn comes from an :class:`omnire_sim.Simulation` of ``scenario`` (a scenario
    file's edits, or none) with the panel's actor edits on top (:meth:`simulation`).

    Args:
        recon: the scene runtime (read only).
        edits: the panel's actor edits (shared with the app).
        max_gaussians: the browser is sent at most this many Gaussians of non-actor nodes
            (a seeded uniform subsample above it; the server render always uses all).
        sky_count: splats of the browser's sky shell (0: no sky in the browser).
        scenario: the simulation to show (default: the scene as reconstructed).
        plugins: loads the runs a scenario inserts actors from.
    """

    def __init__(self, recon, edits: Optional[EditModel] = None, max_gaussians: int = 3_000_000,
                 sky_count: int = 10_000, scenario: Optional[Scenario] = None, plugins=None) -> None:
        self.edits = edits if edits is not None else EditModel()
        self.base = scenario if scenario is not None else Scenario()
        self.plugins = plugins
        self.max_gaussians = max_gaussians
        self.sky_count = sky_count
        self.lock = threading.RLock()
        self.eye: Optional[torch.Tensor] = None
        self._cache: dict[str, _Cached] = {}
        self._counter = 0
        self._assets: dict = {}
        self.set_recon(recon)

    # ------------------------------------------------------------------ structure
    def set_recon(self, recon) -> None:
        """Show ``recon`` (e.g. a new training snapshot); every object is rebuilt. A scenario
        that does not fit ``recon`` raises its ScenarioError (naming line and field)."""
        with self.lock:
            self.recon = recon
            self.scene = recon.scene
            self._cache.clear()
            self._sim = None
            base = Simulation(recon, self.base, self.plugins, assets=self._assets)  # checks the scenario
            self._assets = base.assets
            self.actors: dict[str, ActorInfo] = {}
            self.node_kinds: dict[str, str] = {}
            removed = {a.key for a in base.actors if a.removed and not a.inserted}
            for name, node in recon.nodes.items():
                if isinstance(node, EnvironmentNode):
                    self.node_kinds[name] = "environment"
                elif isinstance(node, ActorNode):
                    self.node_kinds[name] = "actors"
                    for i, tid in enumerate(node.track_ids):
                        if tid not in removed:  # not in the simulated scene: nothing to select
                            self.actors[tid] = _actor_info(recon, tid, name, i)
                else:
                    self.node_kinds[name] = "gaussians"
            for actor in base.actors:
                if actor.inserted:
                    self.actors[actor.key] = _actor_info(actor.owner, actor.node.track_ids[actor.instance],
                                                         actor.node_name, actor.instance, actor.key)
            if self.eye is None:
                self.eye = torch.as_tensor(self.scene.cameras[0].cam_to_world[0, :3, 3], dtype=torch.float32)
            self._sim, self._sim_version = (base, self.edits.version) if not self.edits else (None, -1)

    def simulation(self) -> Simulation:
        """The simulation drawn now: the scenario with the panel's edits (re-resolved after
        every edit)."""
        with self.lock:
            if self._sim is None or self._sim_version != self.edits.version:
                version = self.edits.version
                self._sim = Simulation(self.recon, self.edits.scenario(self.base), self.plugins, assets=self._assets)
                self._sim_version = version
            return self._sim

    def set_edit(self, key: str, edit: ActorEdit) -> None:
        with self.lock:
            self.edits.set(key, edit)

    def clear_edits(self) -> None:
        with self.lock:
            self.edits.clear()

    @property
    def num_frames(self) -> int:
        return self.scene.num_frames

    def time(self, frame: float) -> SceneTime:
        return self.recon.time(min(max(float(frame), 0.0), self.num_frames - 1))

    def set_eye(self, eye) -> None:
        """Evaluate view-dependent colours for viewpoint ``eye`` (3,) from now on."""
        with self.lock:
            self.eye = torch.as_tensor(np.asarray(eye, np.float32))
            self._cache.clear()

    # ------------------------------------------------------------------ objects
    def _splats_for(self, name: str, g: Gaussians, world_means: Optional[torch.Tensor], budget: bool,
                    sh_degree: int) -> tuple[SplatArrays, int]:
        """Cached splats of ``g`` under ``name``: rebuilt only when the tensors changed."""
        tensors = tuple(getattr(g, k) for k in KEYS)
        versions = tuple(t._version for t in tensors)
        hit = self._cache.get(name)
        if hit is not None:
            if all(a is b for a, b in zip(hit.tensors, tensors, strict=True)):
                unchanged = hit.versions == versions  # the same tensors: changed only in place
            else:
                unchanged = all(a.shape == b.shape and torch.equal(a, b)
                                for a, b in zip(hit.tensors, tensors, strict=True))
            if unchanged:
                return hit.splats, hit.version
        keep = None
        if budget and len(g) > self.max_gaussians:
            gen = torch.Generator().manual_seed(0)
            keep = torch.randperm(len(g), generator=gen)[: self.max_gaussians].sort().values
        splats = splat_arrays(g, world_means, self.eye, sh_degree, keep)
        self._counter += 1
        self._cache[name] = _Cached(tensors, versions, splats, self._counter)
        return splats, self._counter

    @staticmethod
    def object_name(group: Drawn, key: str) -> str:
        return f"/actors/insert/{key}" if group.inserted else f"/actors/{group.node_name}/{key}"

    @torch.no_grad()
    def objects_at(self, frame: float) -> dict[str, SceneObject]:
        """Every object of the simulated scene present at ``frame``, by scene name
        (``/nodes/<node>``, ``/actors/<node>/<track id>``, ``/actors/insert/<insert id>``)."""
        t = self.time(frame)
        out: dict[str, SceneObject] = {}
        with self.lock:
            for group in self.recon.drawn(t, self.simulation()):
                if not group.is_actor:
                    res = group.output()
                    if res is None or len(res.gaussians) == 0:
                        continue
                    key = f"/nodes/{group.node_name}"
                    splats, version = self._splats_for(key, res.gaussians, None, True, self.recon.sh_degree())
                    out[key] = SceneObject(key, group.node_name, None, splats, np.zeros(3), np.array([1.0, 0, 0, 0]),
                                           version)
                    continue
                for tid, g, R, tr in self._actor_locals(group):
                    key = self.object_name(group, tid)
                    world = g.means @ R.T + tr
                    splats, version = self._splats_for(key, g, world, False, group.owner.sh_degree())
                    out[key] = SceneObject(key, None if group.inserted else group.node_name, tid, splats,
                                           tr.double().cpu().numpy(), rotmat_to_quat(R.double().cpu()).numpy(), version)
        return out

    def _actor_locals(self, group: Drawn):
        """(key, box-frame Gaussians, R (3, 3), t (3,)) per actor of ``group``: its node draws
        them at the identity pose (posed bodies, deformations and moment kept)."""
        state, node = group.state, group.node
        if len(state.ids) == 0:
            return
        P = len(state.ids)
        local = ActorState(state.ids, torch.eye(3, dtype=state.R.dtype, device=state.R.device).expand(P, 3, 3)
                           .contiguous(), torch.zeros_like(state.t), state.body)
        res = node.gaussians_for(local, group.moment)
        if res is None or res.rows is None:
            return
        instance = node.gaussian_buffers["instance"][res.rows]
        ids, counts = torch.unique_consecutive(instance, return_counts=True)
        slot = {int(i): k for k, i in enumerate(state.ids.tolist())}
        start = 0
        for i, c in zip(ids.tolist(), counts.tolist(), strict=True):
            g = Gaussians(*(getattr(res.gaussians, k)[start:start + c] for k in KEYS))
            k = slot[int(i)]
            yield group.keys[k], g, state.R[k], state.t[k]
            start += c

    def sky(self) -> Optional[SplatArrays]:
        """The browser's sky shell (from the first environment node with a map), or None."""
        if self.sky_count <= 0:
            return None
        for node in self.recon.environment_nodes().values():
            if hasattr(node, "environment_map"):
                centres = np.stack([c.cam_to_world[:, :3, 3] for c in self.scene.cameras]).reshape(-1, 3)
                radius = max(300.0, 4.0 * float(self.recon.scene_radius))
                return sky_splats(node.environment_map(), centres.mean(0), radius, self.sky_count)
        return None

    def environment_nodes(self) -> list[str]:
        return [n for n, k in self.node_kinds.items() if k == "environment"]

    # ------------------------------------------------------------------ boxes, picking, cameras
    @torch.no_grad()
    def actor_boxes(self, frame: float) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Box (R (3, 3), centre (3,), size (3,)) of every actor drawn at ``frame`` in the
        simulated scene, by track id / insert id."""
        t = self.time(frame)
        boxes = {}
        with self.lock:
            for group in drawn_actors(self.simulation(), t):
                for k, key in enumerate(group.keys):
                    boxes[key] = (group.state.R[k].double().cpu().numpy(), group.state.t[k].double().cpu().numpy(),
                                  np.asarray(self.actors[key].size))
        return boxes

    def pick(self, origin, direction, frame: float) -> Optional[str]:
        """The actor whose box the ray (origin (3,), direction (3,)) enters first, or None."""
        o, d = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
        best, best_t = None, math.inf
        for tid, (R, c, size) in self.actor_boxes(frame).items():
            lo_o, lo_d = R.T @ (o - c), R.T @ d  # ray in the box frame
            half = size / 2
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-half - lo_o) / lo_d, (half - lo_o) / lo_d
            near = np.nanmax(np.minimum(t1, t2))
            far = np.nanmin(np.maximum(t1, t2))
            if near <= far and far > 0 and max(near, 0.0) < best_t:
                best, best_t = tid, max(near, 0.0)
        return best

    def cameras_at(self, frame: float) -> list[tuple[str, np.ndarray, np.ndarray, int, int]]:
        """The dataset cameras at the recorded frame nearest ``frame``: (name, cam_to_world
        (4, 4), K (3, 3), width, height)."""
        f = int(round(min(max(frame, 0), self.num_frames - 1)))
        return [(c.name, c.cam_to_world[f], c.intrinsics, c.width, c.height) for c in self.scene.cameras]

    # ------------------------------------------------------------------ LiDAR
    @property
    def renders_lidar(self) -> bool:
        """The run learned LiDAR (``--method.lidar.enabled``) and its scene has sweeps."""
        lidar = self.scene.lidar
        return bool(self.recon.renders_lidar and lidar is not None and len(lidar.available_frames()))

    @torch.no_grad()
    def lidar_sweep(self, frame: float) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """The rendered sweep of the simulated scene at ``frame`` (``omnire_sim.cli.sim_sweep``,
        as ``omnire sim --lidar`` renders it: the edits apply, the panel's node toggles,
        which only choose the splats drawn, do not): (points, structured (P,) of
        ``omnire.api.POINT_FIELDS``; sensor positions (P, 3) when each point's ray fired).
        None when the run learned no LiDAR."""
        if not self.renders_lidar:
            return None
        t = self.time(frame)
        with self.lock:
            points = sim_sweep(self.simulation(), t)
            sensor = sensor_path(self.scene).at(points["time"])[:, :3, 3]
        return points, sensor

    # ------------------------------------------------------------------ server render
    @torch.no_grad()
    def render(self, camera: Camera, frame: float, hidden: frozenset[str] = frozenset()) -> np.ndarray:
        """(H, W, 3) float image of ``camera`` at ``frame``: ``Simulation.render`` of the
        simulated scene (the run's rasterizer, SH and sky included); nodes in ``hidden`` left
        out (inserted actors belong to no node of this run and stay)."""
        t = self.time(frame)
        with self.lock:
            return self.simulation().render(camera, t, hidden=frozenset(hidden)).rgb.clamp(0, 1).cpu().numpy()


def _actor_info(owner, track: str, node: str, instance: int, insert: Optional[str] = None) -> ActorInfo:
    """The panel's description of ``track`` of ``owner``'s scene (an inserted actor: keyed
    by its insert id)."""
    tr = next((t for t in owner.scene.tracks if t.track_id == track), None)
    frames = np.flatnonzero(tr.present) if tr is not None and tr.present.any() else np.zeros(1, int)
    return ActorInfo(insert or track, tr.class_name if tr else "?", tr.category if tr else "?", node, instance,
                     tuple(float(s) for s in (tr.size if tr is not None else (1, 1, 1))),
                     (int(frames.min()), int(frames.max())), inserted_from=track if insert else None)
