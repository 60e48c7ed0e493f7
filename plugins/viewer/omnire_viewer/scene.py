"""The scene as the viewer shows it, without any web machinery: one object per non-actor
node and per actor, each in its own frame with a world pose; actor boxes for picking;
dataset cameras; and the server render of any camera with the real rasterizer.

Actors are drawn by their node at the identity pose (their box frame at the moment: posed
and skinned for pedestrians, deformed for deformable actors) and placed by their box pose,
so moving a rigid actor along its track only moves its object; objects whose Gaussians
change (pedestrians re-skinned for a new frame) are rebuilt. Every state goes through
:func:`omnire_viewer.edits.apply_edits` first.
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
    EnvironmentNode,
    Gaussians,
    RasterSettings,
    SceneTime,
    Splats,
    rotmat_to_quat,
)
from omnire_viewer.edits import EditModel, apply_edits
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
    """First and last frame it is present."""

    def describe(self) -> str:
        return (f"**{self.track_id}**: {self.class_name} ({self.category}), node `{self.node}`, "
                f"box {self.size[0]:.1f} x {self.size[1]:.1f} x {self.size[2]:.1f} m, "
                f"frames {self.frames[0]}-{self.frames[1]}")


@dataclasses.dataclass
class SceneObject:
    """A set of splats with a world pose (box-to-world for actors, identity otherwise).

    ``version`` changes whenever ``splats`` do (the app re-sends the object then)."""

    name: str
    node: str
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
    """The viewer's model of a :class:`~omnire.runtime.Reconstruction`.

    Args:
        recon: the scene runtime (read only).
        edits: the actor edits (shared with the app).
        max_gaussians: the browser is sent at most this many Gaussians of non-actor nodes
            (a seeded uniform subsample above it; the server render always uses all).
        sky_splats: splats of the browser's sky shell (0: no sky in the browser).
    """

    def __init__(self, recon, edits: Optional[EditModel] = None, max_gaussians: int = 3_000_000,
                 sky_count: int = 10_000) -> None:
        self.edits = edits if edits is not None else EditModel()
        self.max_gaussians = max_gaussians
        self.sky_count = sky_count
        self.lock = threading.RLock()
        self.eye: Optional[torch.Tensor] = None
        self._cache: dict[str, _Cached] = {}
        self._counter = 0
        self.set_recon(recon)

    # ------------------------------------------------------------------ structure
    def set_recon(self, recon) -> None:
        """Show ``recon`` (e.g. a new training snapshot); every object is rebuilt."""
        with self.lock:
            self.recon = recon
            self.scene = recon.scene
            self.model = recon.model
            self._cache.clear()
            tracks = {t.track_id: t for t in self.scene.tracks}
            self.actors: dict[str, ActorInfo] = {}
            self.node_kinds: dict[str, str] = {}
            for name, node in self.model.nodes.items():
                if isinstance(node, EnvironmentNode):
                    self.node_kinds[name] = "environment"
                elif isinstance(node, ActorNode):
                    self.node_kinds[name] = "actors"
                    for i, tid in enumerate(node.track_ids):
                        tr = tracks.get(tid)
                        frames = np.flatnonzero(tr.present) if tr is not None else np.zeros(1, int)
                        self.actors[tid] = ActorInfo(tid, tr.class_name if tr else "?", tr.category if tr else "?",
                                                     name, i, tuple(float(s) for s in (tr.size if tr else (1, 1, 1))),
                                                     (int(frames.min()), int(frames.max())))
                else:
                    self.node_kinds[name] = "gaussians"
            if self.eye is None:
                self.eye = torch.as_tensor(self.scene.cameras[0].cam_to_world[0, :3, 3], dtype=torch.float32)

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
    def _splats_for(self, name: str, g: Gaussians, world_means: Optional[torch.Tensor],
                    budget: bool) -> tuple[SplatArrays, int]:
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
        splats = splat_arrays(g, world_means, self.eye, self.recon.sh_degree(), keep)
        self._counter += 1
        self._cache[name] = _Cached(tensors, versions, splats, self._counter)
        return splats, self._counter

    def edited_state(self, node: ActorNode, t: SceneTime) -> ActorState:
        return apply_edits(self.edits, node, node.state_at(t), t)

    @torch.no_grad()
    def objects_at(self, frame: float) -> dict[str, SceneObject]:
        """Every object present at ``frame`` after the edits, by scene name
        (``/nodes/<node>`` or ``/actors/<node>/<track id>``)."""
        t = self.time(frame)
        out: dict[str, SceneObject] = {}
        with self.lock:
            for name, node in self.model.nodes.items():
                kind = self.node_kinds[name]
                if kind == "gaussians":
                    res = node.gaussians_at(t, None, None)
                    if res is None or len(res.gaussians) == 0:
                        continue
                    key = f"/nodes/{name}"
                    splats, version = self._splats_for(key, res.gaussians, None, budget=True)
                    out[key] = SceneObject(key, name, None, splats, np.zeros(3), np.array([1.0, 0, 0, 0]), version)
                elif kind == "actors":
                    state = self.edited_state(node, t)
                    for tid, g, R, tr in self._actor_locals(node, state, t):
                        key = f"/actors/{name}/{tid}"
                        world = g.means @ R.T + tr
                        splats, version = self._splats_for(key, g, world, budget=False)
                        out[key] = SceneObject(key, name, tid, splats, tr.double().numpy(),
                                               rotmat_to_quat(R.double()).numpy(), version)
        return out

    def _actor_locals(self, node: ActorNode, state: ActorState, t: SceneTime):
        """(track id, box-frame Gaussians, R (3, 3), t (3,)) per actor of ``state``."""
        if len(state.ids) == 0:
            return
        P = len(state.ids)
        local = ActorState(state.ids, torch.eye(3, dtype=state.R.dtype).expand(P, 3, 3).contiguous(),
                           torch.zeros_like(state.t), state.body)
        res = node.gaussians_for(local, t)
        if res is None or res.rows is None:
            return
        instance = node.gaussian_buffers["instance"][res.rows]
        ids, counts = torch.unique_consecutive(instance, return_counts=True)
        slot = {int(i): k for k, i in enumerate(state.ids.tolist())}
        start = 0
        for i, c in zip(ids.tolist(), counts.tolist(), strict=True):
            g = Gaussians(*(getattr(res.gaussians, k)[start:start + c] for k in KEYS))
            k = slot[int(i)]
            yield node.track_ids[int(i)], g, state.R[k], state.t[k]
            start += c

    def sky(self) -> Optional[SplatArrays]:
        """The browser's sky shell (from the first environment node with a map), or None."""
        if self.sky_count <= 0:
            return None
        for node in self.model.nodes.values():
            if isinstance(node, EnvironmentNode) and hasattr(node, "environment_map"):
                centres = np.stack([c.cam_to_world[:, :3, 3] for c in self.scene.cameras]).reshape(-1, 3)
                radius = max(300.0, 4.0 * float(self.model.scene_radius))
                return sky_splats(node.environment_map(), centres.mean(0), radius, self.sky_count)
        return None

    def environment_nodes(self) -> list[str]:
        return [n for n, k in self.node_kinds.items() if k == "environment"]

    # ------------------------------------------------------------------ boxes, picking, cameras
    @torch.no_grad()
    def actor_boxes(self, frame: float) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Box (R (3, 3), centre (3,), size (3,)) of every actor drawn at ``frame`` (edited)."""
        t = self.time(frame)
        boxes = {}
        with self.lock:
            for name, node in self.model.nodes.items():
                if self.node_kinds[name] != "actors":
                    continue
                state = self.edited_state(node, t)
                for k, i in enumerate(state.ids.tolist()):
                    tid = node.track_ids[i]
                    boxes[tid] = (state.R[k].double().numpy(), state.t[k].double().numpy(),
                                  np.asarray(self.actors[tid].size))
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

    # ------------------------------------------------------------------ server render
    @torch.no_grad()
    def render(self, camera: Camera, frame: float, hidden: frozenset[str] = frozenset()) -> np.ndarray:
        """(H, W, 3) float image of ``camera`` at ``frame`` by the real rasterizer, SH and sky
        included; nodes in ``hidden`` left out; actor edits applied."""
        t = self.time(frame)
        with self.lock:
            if not self.edits:
                return self.recon.render(camera, t, hidden=hidden).rgb.clamp(0, 1).cpu().numpy()
            return self._render_edited(camera, t, hidden).clamp(0, 1).cpu().numpy()

    def _render_edited(self, camera: Camera, t: SceneTime, hidden: frozenset[str]) -> torch.Tensor:
        """The runtime's composition (Gaussians of every node, SH at the camera, rasterize,
        environment under the Gaussians) with the actor states edited."""
        parts = []
        for name, node in self.model.nodes.items():
            kind = self.node_kinds[name]
            if name in hidden or kind == "environment":
                continue
            if kind == "actors":
                state = self.edited_state(node, t)
                res = node.gaussians_for(state, t, camera) if len(state.ids) else None
            else:
                res = node.gaussians_at(t, camera, None)
            if res is not None and len(res.gaussians):
                parts.append(res.gaussians)
        env = [n for n in self.environment_nodes() if n not in hidden]
        device = camera.device
        background = None if env else torch.tensor(self.recon.method.background_color, dtype=torch.float32,
                                                   device=device)
        H, W = camera.height, camera.width
        if parts:
            g = Gaussians.cat(parts)
            splats = Splats(g.means, g.quats, g.activated_scales, g.activated_opacities,
                            g.colors(camera.center, self.recon.sh_degree()))
            out = self.model.rasterizer.rasterize(splats, camera, RasterSettings(background=background))
            rgb, alpha = out.rgb, out.alpha
        else:
            rgb = (background if background is not None else torch.zeros(3, device=device)).expand(H, W, 3)
            alpha = torch.zeros(H, W, 1, device=device)
        for name in env:
            rgb = rgb + (1.0 - alpha) * self.model.nodes[name].render_environment(camera, t)
        return rgb
