"""The scene graph: nodes built from a method config, rendered per view.

Per view (camera c, frame t): every Gaussian node present at t returns its world-space
Gaussians -> concatenate -> colours from SH at the camera centre -> rasterize -> composite
the environment (sky) node under the Gaussians: C = C_gs + (1 - O_gs) C_env.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Optional

import numpy as np
import torch
from torch import nn

from omnire.camera import PinholeCamera, in_frustum
from omnire.data.scene import SceneData, View
from omnire.gaussians import Gaussians
from omnire.nodes.base import Node, NodeContext
from omnire.rasterization import Rasterizer
from omnire.strategy import NodeSlice


class ModelBuildError(ValueError):
    """The method cannot be assembled (unknown node type, ...)."""


@dataclasses.dataclass
class RenderResult:
    """Rendered view. rgb/depth/alpha are (H, W, C); ``slices`` map rendered rows to nodes."""

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    absgrad2d: torch.Tensor
    radii: torch.Tensor
    slices: list[NodeSlice]
    num_gaussians: int


CULL_SIGMAS = 4.0
CULL_PAD_PIXELS = 3


def cull_to_frustum(g: Gaussians, rows: Optional[torch.Tensor], camera: PinholeCamera
                    ) -> tuple[Gaussians, Optional[torch.Tensor]]:
    """Keep the Gaussians whose ``CULL_SIGMAS``-sigma sphere reaches the camera frustum,
    widened by ``CULL_PAD_PIXELS``; no other can be drawn, so the image is unchanged.
    Rasterizers cut splats where alpha < 1/255, at most sqrt(2 ln 255) = 3.33 sigma of the
    (affine-projected) 2D covariance, plus a 0.3 px^2 low-pass dilation (1.8 px at that
    cut) and half a pixel of rounding; 4 sigma and 3 px leave room for the affine
    approximation near the borders. ``rows`` (the node rows of ``g``, None = all in order)
    is narrowed to match."""
    reach = CULL_SIGMAS * torch.exp(g.scales.detach().max(dim=-1).values)
    keep = torch.nonzero(in_frustum(g.means.detach(), camera.padded(CULL_PAD_PIXELS), reach)).squeeze(1)
    if len(keep) == len(g):
        return g, rows
    return g.subset(keep), (keep if rows is None else rows[keep])


def scene_radius(scene: SceneData) -> float:
    """Scene scale: 1.1 x the largest distance of a training camera from their mean (>= 1 m)."""
    centers = np.stack([c.cam_to_world[f, :3, 3] for c in scene.cameras for f in scene.train_frames])
    return float(max(1.0, 1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max()))


def assign_tracks(scene: SceneData, node_specs: dict[str, Any]) -> dict[str, list]:
    """Map each track to the enabled node type that takes its category (highest priority;
    ``accepts`` may refuse). Tracks no enabled node takes stay in the background."""
    assigned: dict[str, list] = {name: [] for name in node_specs}
    for track in scene.tracks:
        best = None
        for name, spec in node_specs.items():
            if track.category not in spec.categories:
                continue
            if spec.accepts is not None and not spec.accepts(track, scene):
                continue
            if best is None or spec.priority > node_specs[best].priority:
                best = name
        if best is not None:
            assigned[best].append(track)
    return assigned


class SceneModel(nn.Module):
    def __init__(self, method, scene: SceneData, node_registry, images, rasterizer: Rasterizer,
                 device: torch.device, seed: int = 0) -> None:
        super().__init__()
        self.method = method
        self.scene = scene
        self.rasterizer = rasterizer
        self.device = device
        unknown = [n for n in method.disable if n not in method.nodes]
        if unknown:
            raise ModelBuildError(f"--method.disable {unknown}: not node types of this method ({list(method.nodes)})")
        enabled = {n: c for n, c in method.nodes.items() if n not in method.disable}
        specs = {}
        for name in enabled:
            if name not in node_registry:
                raise ModelBuildError(f"method uses node type {name!r}, which no installed plugin registers; "
                                      f"registered: {node_registry.names()}")
            specs[name] = node_registry.get(name)
        assigned = assign_tracks(scene, specs)
        self.assignment = {name: [t.track_id for t in tracks] for name, tracks in assigned.items()}
        actor_tracks = [t for name, tracks in assigned.items() for t in tracks]
        generator = torch.Generator().manual_seed(seed)
        radius = scene_radius(scene)
        self.scene_radius = radius
        nodes = {}
        for name, cfg in enabled.items():
            is_actor_type = bool(specs[name].categories)
            if is_actor_type and not assigned[name]:
                continue  # skip what the scene does not need: no actors, no node
            ctx = NodeContext(scene, images, radius, device, generator,
                              excluded_tracks=[] if is_actor_type else actor_tracks)
            nodes[name] = cfg.setup(context=ctx, tracks=assigned[name])
        self.nodes = nn.ModuleDict(nodes)
        self._K = [torch.as_tensor(c.intrinsics, dtype=torch.float32, device=device) for c in scene.cameras]
        self._c2w = [torch.as_tensor(c.cam_to_world, dtype=torch.float32, device=device) for c in scene.cameras]
        self._bg = torch.tensor(method.background_color, dtype=torch.float32, device=device)

    def gaussian_nodes(self) -> dict[str, Node]:
        return {n: m for n, m in self.nodes.items() if not m.is_environment}

    def num_gaussians(self) -> int:
        return sum(m.num_gaussians for m in self.gaussian_nodes().values())

    def camera(self, view: View) -> tuple[torch.Tensor, torch.Tensor, int, int]:
        """(K (3,3), cam_to_world (4,4), width, height) of a view."""
        cam = self.scene.cameras[view.camera]
        return self._K[view.camera], self._c2w[view.camera][view.frame], cam.width, cam.height

    def render(self, view: View, sh_degree: int = 3, camera_override: Optional[tuple] = None,
               time_override: Optional[float] = None, step: Optional[int] = None) -> RenderResult:
        """Render ``view``. ``camera_override`` = (K, cam_to_world, width, height) renders the
        scene at the view's frame from another camera (novel trajectories). ``step`` is the
        training step (None: the trained model, e.g. for evaluation)."""
        K, c2w, W, H = camera_override or self.camera(view)
        frame = view.frame
        time = float(self.scene.frame_timestamps[frame]) if time_override is None else time_override
        camera = PinholeCamera(K, c2w, W, H)
        parts, slices, start = [], [], 0
        for name, node in self.gaussian_nodes().items():
            out = node.gaussians_at(frame, time, step, camera=camera)
            if out is None:
                continue
            g, rows = out
            if self.method.cull_to_view and len(g):
                g, rows = cull_to_frustum(g, rows, camera)
            parts.append(g)
            slices.append(NodeSlice(name, start, start + len(g), rows))
            start += len(g)
        env = [m for m in self.nodes.values() if m.is_environment]
        background = None if env else self._bg
        viewmat = torch.linalg.inv(c2w)
        if parts:
            g = Gaussians.cat(parts)
            colors = g.colors(c2w[:3, 3], sh_degree)
            out = self.rasterizer.rasterize(
                g.means, g.quats, g.activated_scales, g.activated_opacities, colors, viewmat, K, W, H,
                background=background,
            )
            rgb, depth, alpha, absgrad, radii = out.rgb, out.depth, out.alpha, out.absgrad2d, out.radii
        else:
            rgb = (background if background is not None else torch.zeros(3, device=self.device)).expand(H, W, 3)
            depth = torch.zeros(H, W, 1, device=self.device)
            alpha = torch.zeros(H, W, 1, device=self.device)
            absgrad = torch.zeros(0, 2, device=self.device)
            radii = torch.zeros(0, dtype=torch.int32, device=self.device)
        for node in env:
            rgb = rgb + (1.0 - alpha) * node.render_environment(K, c2w, W, H, frame, time)
        return RenderResult(rgb, depth, alpha, absgrad, radii, slices, start)
