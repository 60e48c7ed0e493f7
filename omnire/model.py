"""The scene graph: nodes built from a method config, rendered per (camera, moment).

Per view: every Gaussian node present at the moment returns its world-space Gaussians ->
concatenate -> colours from SH at the camera centre -> rasterize -> composite the
environment (sky) node under the Gaussians: C = C_gs + (1 - O_gs) C_env.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Optional

import numpy as np
import torch
from torch import nn

from omnire.camera import Camera, gaussian_reach, may_be_drawn
from omnire.camerapose import CameraPoseRefinement
from omnire.data.scene import SceneData, SceneTime
from omnire.errors import UserError
from omnire.exposure import ExposureCompensation
from omnire.gaussians import Gaussians
from omnire.lidarmodel import LidarRender, activate, decode, lidar_features_for
from omnire.lidarprojection import may_reach
from omnire.nodes.actors import observed_in_training
from omnire.nodes.base import EnvironmentNode, Node, NodeContext, NodeOutput
from omnire.rasterization import LidarSettings, Rasterizer, RasterSettings, Splats
from omnire.strategy import NodeSlice


class ModelBuildError(UserError):
    """The method cannot be assembled (unknown node type, ...)."""


# Renders without autograd evaluate the environment nodes only at pixels whose final
# transmittance T = 1 - alpha exceeds this. Elsewhere the skipped term T * C_env, with C_env
# in [0, 1], changes the pixel by at most 1e-3 per environment node, times the exposure's
# near-identity colour transform (1.07e-3 at most on the trained demo run): about a quarter
# of an 8-bit step (1 / 255 = 3.9e-3). It must exceed the rasterizers' own 1e-4 stop
# (they composite while T stays above it, so no pixel ends below) to skip anything.
ENVIRONMENT_MIN_TRANSMITTANCE = 1e-3


@dataclasses.dataclass
class RenderResult:
    """A rendered view. rgb/depth/alpha are (H, W, C); ``slices`` map rendered rows to
    nodes; ``outputs`` hold what each node produced (for its regulariser); ``timings``: wall
    seconds of the render's stages by name (``nodes``, ``raster`` and the rasterizer's own
    ``raster.*``, ``environment``), as far as the path measured them (profiles only);
    ``environment_pixels``: the pixels at which the environment nodes were evaluated (all of
    them with autograd on, fewer without: :meth:`SceneModel.finish_image`; 0 without any)."""

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    absgrad2d: torch.Tensor
    radii: torch.Tensor
    slices: list[NodeSlice]
    num_gaussians: int
    outputs: dict[str, NodeOutput] = dataclasses.field(default_factory=dict)
    timings: dict[str, float] = dataclasses.field(default_factory=dict)
    environment_pixels: int = 0


def cull_to_frustum(g: Gaussians, rows: Optional[torch.Tensor], camera: Camera
                    ) -> tuple[Gaussians, Optional[torch.Tensor]]:
    """Keep the Gaussians whose ``CULL_SIGMAS``-sigma sphere reaches the camera frustum,
    widened by ``CULL_PAD_PIXELS`` (:func:`omnire.camera.may_be_drawn`); no other can be
    drawn, so the image is unchanged. ``rows`` (the node rows of ``g``, None = all in order)
    is narrowed to match."""
    reach = gaussian_reach(g.scales)
    keep = torch.nonzero(may_be_drawn(g.means.detach(), reach, camera)).squeeze(1)
    if len(keep) == len(g):
        return g, rows
    return g.subset(keep), (keep if rows is None else rows[keep])


def scene_radius(scene: SceneData) -> float:
    """Scene scale: 1.1 x the largest distance of a training camera from their mean (>= 1 m)."""
    centers = np.stack([c.cam_to_world[f, :3, 3] for c in scene.cameras for f in scene.train_frames])
    return float(max(1.0, 1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max()))


def assign_tracks(scene: SceneData, node_specs: dict[str, Any], lidar_learning: bool = False) -> dict[str, list]:
    """Map each track that training observes (:func:`~omnire.nodes.actors.observed_in_training`:
    a camera sees it, or the LiDAR does when ``lidar_learning``) to the enabled node type that
    takes its category (highest priority; ``accepts`` may refuse). Other tracks stay in the
    background."""
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
        # Asked last: it projects the box into every training view (and counts returns in
        # every sweep), work a track no enabled node takes (every track of 3dgs) need not do.
        if best is not None and observed_in_training(track, scene, lidar_learning):
            assigned[best].append(track)
    return assigned


def enabled_node_specs(method, node_registry) -> dict[str, Any]:
    """The node-type specs a method enables (its nodes minus ``--method.disable``)."""
    unknown = [n for n in method.disable if n not in method.nodes]
    if unknown:
        raise ModelBuildError(f"--method.disable {unknown}: not node types of this method ({list(method.nodes)})")
    specs = {}
    for name in method.nodes:
        if name in method.disable:
            continue
        if name not in node_registry:
            raise ModelBuildError(f"method uses node type {name!r}, which no installed plugin registers; "
                                  f"registered: {node_registry.names()}")
        specs[name] = node_registry.get(name)
    return specs


class SceneModel(nn.Module):
    """The nodes of one scene, and how a view of them is rendered.

    ``use_fused_training`` (default True; an instance may set it False): take the fused
    training path (:meth:`fused_training`) when the rasterizer declares it; False forces
    :meth:`assemble` + :meth:`composite` with autograd (comparisons, ``omnire bench step``).

    Args:
        method: the :class:`~omnire.method.MethodConfig`.
        scene: the scene (prepared: see :meth:`prepare`).
        specs: node-type specs by name (:func:`enabled_node_specs`).
        assignment: track ids per node type; None assigns the scene's tracks now.
        images: ImageCache for data-driven initialisation; None when restoring a checkpoint.
        rasterizer, device, seed: as named.
        restoring: build empty nodes to receive a checkpoint (no LiDAR or image reading).
        capabilities: the optional paths the rasterizer's spec declares
            (:data:`omnire.rasterization.CAPABILITIES`); only those are taken.
    """

    use_fused_training: bool = True

    def __init__(self, method, scene: SceneData, specs: dict[str, Any], images, rasterizer: Rasterizer,
                 device: torch.device, seed: int = 0, assignment: Optional[dict[str, list[str]]] = None,
                 restoring: bool = False, capabilities: frozenset[str] = frozenset()) -> None:
        super().__init__()
        self.method = method
        self.scene = scene
        self.rasterizer = rasterizer
        self.capabilities = frozenset(capabilities)
        self.device = device
        if assignment is None:
            assigned = assign_tracks(scene, specs, lidar_learning=method.lidar.enabled and scene.lidar is not None)
        else:
            by_id = {t.track_id: t for t in scene.tracks}
            missing = sorted({i for ids in assignment.values() for i in ids} - set(by_id))
            if missing:
                raise ModelBuildError(f"the recorded node assignment names tracks the scene does not have: "
                                      f"{missing[:5]}")
            assigned = {name: [by_id[i] for i in assignment.get(name, [])] for name in specs}
        self.assignment = {name: [t.track_id for t in tracks] for name, tracks in assigned.items()}
        actor_tracks = [t for tracks in assigned.values() for t in tracks]
        generator = torch.Generator().manual_seed(seed)
        radius = scene_radius(scene)
        self.scene_radius = radius
        self.lidar_features = lidar_features_for(method.lidar, scene)
        if self.lidar_features is not None and "lidar" not in self.capabilities:
            raise ModelBuildError(f"--method.lidar.enabled: the rasterizer {rasterizer.name!r} cannot render LiDAR "
                                  "(no 'lidar' capability); choose one that can (omnire plugins lists them)")
        nodes = {}
        for name, spec in specs.items():
            is_actor_type = bool(spec.categories)
            if is_actor_type and not assigned[name]:
                continue  # skip what the scene does not need: no actors, no node
            ctx = NodeContext(scene, images, radius, device, generator,
                              excluded_tracks=[] if is_actor_type else actor_tracks, restoring=restoring,
                              lidar=self.lidar_features)
            nodes[name] = method.nodes[name].setup(context=ctx, tracks=assigned[name])
        self.nodes = nn.ModuleDict(nodes)
        self._background = torch.tensor(method.background_color, dtype=torch.float32, device=device)
        self.exposure: Optional[ExposureCompensation] = None
        if method.exposure:
            self.exposure = ExposureCompensation([c.name for c in scene.cameras], scene.num_frames,
                                                 scene.train_frames, method.exposure_lr, device)
        self.camera_poses: Optional[CameraPoseRefinement] = None
        if method.camera_pose_refinement:
            self.camera_poses = CameraPoseRefinement([c.name for c in scene.cameras], scene.num_frames,
                                                     scene.train_frames, method.camera_pose_lr, device)

    def optimizable(self) -> dict[str, Any]:
        """What the optimisers step, by name: the nodes, plus ``exposure`` and
        ``camera_poses`` when learned."""
        out: dict[str, Any] = dict(self.nodes)
        if self.exposure is not None:
            out["exposure"] = self.exposure
        if self.camera_poses is not None:
            out["camera_poses"] = self.camera_poses
        return out

    def seen_from(self, parts: list[tuple[str, Optional[NodeOutput]]], camera: Camera, t: SceneTime
                  ) -> list[tuple[str, Optional[NodeOutput]]]:
        """Node outputs as ``camera`` sees them at its refined pose (omnire/camerapose.py):
        moved by the correction's world transform; unchanged without refinement or for an
        unrecorded camera."""
        transform = self.camera_poses.world_transform(camera, t) if self.camera_poses is not None else None
        if transform is None:
            return parts
        return [(name, None if out is None else out.with_gaussians(out.gaussians.transform(*transform)))
                for name, out in parts]

    def finish_image(self, rgb: torch.Tensor, alpha: torch.Tensor, env: dict[str, EnvironmentNode],
                     camera: Camera, t: SceneTime) -> tuple[torch.Tensor, int]:
        """Composite the environment nodes ``env`` under the Gaussians' (H, W, 3) ``rgb``
        (coverage ``alpha`` (H, W, 1)), then the recorded camera's exposure: (H, W, 3) image,
        the number of pixels at which ``env`` was evaluated.

        Without autograd only at pixels whose transmittance exceeds
        :data:`ENVIRONMENT_MIN_TRANSMITTANCE` (the others change by at most that, see
        there; the evaluated ones get the same values). With autograd at every pixel: the
        environment's gradient T dL/dC is kept exact everywhere in training."""
        transmittance = 1.0 - alpha
        pixels = None
        if env and not torch.is_grad_enabled():
            pixels = torch.nonzero(transmittance.reshape(-1) > ENVIRONMENT_MIN_TRANSMITTANCE).squeeze(1)
            if len(pixels) == transmittance.numel():
                pixels = None
        evaluated = transmittance.numel() if env else 0
        if pixels is None:
            for node in env.values():
                rgb = rgb + transmittance * node.render_environment(camera, t)
        elif len(pixels):
            weight = transmittance.reshape(-1, 1)[pixels]
            under = sum(weight * node.render_environment(camera, t, pixels) for node in env.values())
            rgb = rgb.reshape(-1, 3).index_add(0, pixels, under).reshape(rgb.shape)
            evaluated = len(pixels)
        else:
            evaluated = 0
        if self.exposure is not None:
            rgb = self.exposure.apply(rgb, camera.name, t)
        return rgb, evaluated

    def gaussian_nodes(self) -> dict[str, Node]:
        return {n: m for n, m in self.nodes.items() if not isinstance(m, EnvironmentNode)}

    def environment_nodes(self) -> dict[str, EnvironmentNode]:
        return {n: m for n, m in self.nodes.items() if isinstance(m, EnvironmentNode)}

    def num_gaussians(self) -> int:
        return sum(m.num_gaussians for m in self.gaussian_nodes().values())

    def gather(self, camera: Optional[Camera], t: SceneTime, step: Optional[int] = None,
               hidden: frozenset[str] = frozenset()) -> tuple[Optional[Gaussians], list[NodeSlice], dict[str, NodeOutput]]:
        """World-space Gaussians of every node present at ``t`` (culled to ``camera`` when
        the method says so and a camera is given; as it sees them at its refined pose), the
        node slices of the concatenation and each node's output. Nodes named in ``hidden``
        are left out."""
        parts = self.node_parts(camera, t, step, hidden)
        return self.assemble(self.seen_from(parts, camera, t) if camera is not None else parts, camera)

    def node_parts(self, camera: Optional[Camera], t: SceneTime, step: Optional[int] = None,
                   hidden: frozenset[str] = frozenset()) -> list[tuple[str, Optional[NodeOutput]]]:
        """(name, output) of every Gaussian node not in ``hidden`` at moment ``t``, each told
        :meth:`node_camera`."""
        seen_by = self.node_camera(camera, t)
        return [(name, node.gaussians_at(t, seen_by, step)) for name, node in self.gaussian_nodes().items()
                if name not in hidden]

    def node_camera(self, camera: Optional[Camera], t: SceneTime) -> Optional[Camera]:
        """The camera to hand the nodes when ``camera`` renders moment ``t``: with
        ``cull_to_view``, ``camera`` at its refined pose, the camera that sees their Gaussians
        as they are (:meth:`seen_from` moves the Gaussians instead), so what they skip as out
        of view is; without, None (every Gaussian)."""
        if camera is None or not self.method.cull_to_view:
            return None
        if self.camera_poses is None:
            return camera
        with torch.no_grad():
            return self.camera_poses.refined_camera(camera, t)

    def assemble(self, parts: list[tuple[str, Optional[NodeOutput]]], camera: Optional[Camera]
                 ) -> tuple[Optional[Gaussians], list[NodeSlice], dict[str, NodeOutput]]:
        """Concatenate node outputs (name, output or None) into one set, each culled to
        ``camera`` when the method says so: (Gaussians or None, slices, outputs by name).
        :meth:`gather` uses it for the recorded scene; editing tools pass their own parts
        (e.g. actors in edited states, actors of other runs)."""
        gs, slices, outputs, start = [], [], {}, 0
        for name, out in parts:
            if out is None:
                continue
            outputs[name] = out
            g, rows = out.gaussians, out.rows
            if self.method.cull_to_view and camera is not None and len(g):
                g, rows = cull_to_frustum(g, rows, camera)
            gs.append(g)
            slices.append(NodeSlice(name, start, start + len(g), rows))
            start += len(g)
        return (Gaussians.cat(gs) if gs else None), slices, outputs

    def render(self, camera: Camera, t: SceneTime, sh_degree: int = 3, step: Optional[int] = None,
               hidden: frozenset[str] = frozenset()) -> RenderResult:
        """Render the scene at moment ``t`` through ``camera``. ``step`` is the training
        step (None: the trained model, e.g. for evaluation and rendering); nodes in
        ``hidden`` are not drawn (e.g. the sky, for renders of the Gaussians alone)."""
        if self.fast_inference() or self.fused_training():
            return self.render_parts(self.node_parts(camera, t, step, hidden), camera, t, sh_degree, hidden)
        g, slices, outputs = self.gather(camera, t, step, hidden)
        return self.composite(g, slices, outputs, camera, t, sh_degree, hidden)

    def fast_inference(self) -> bool:
        """True when renders take the inference path: autograd is off and the rasterizer
        declares the ``inference`` capability (``rasterize_gaussians``: raw Gaussians,
        activation, SH colour and view culling natively, nothing kept for a backward pass). Same pixels as the training path
        up to float rounding (tests: plugins/cpu-rasterizer/tests/test_cpu_raster_inference.py,
        plugins/sim/tests/test_fast_render.py)."""
        return not torch.is_grad_enabled() and "inference" in self.capabilities

    def fused_training(self) -> bool:
        """True when renders with autograd take the fused training path: the rasterizer
        declares ``fused_training`` and renders raw Gaussians in parts with gradients
        (``rasterize_gaussians_train``:
        activation, SH colour and view culling in its kernel, nothing concatenated). Same
        pixels and gradients as :meth:`gather` + :meth:`composite` up to float rounding, and
        the same densification statistics: the slices cover the node outputs uncut, rows
        the kernel rejected have radius 0 and no AbsGrad, and ``num_gaussians`` counts the
        rows not rejected (tests/test_fused_training.py,
        plugins/cpu-rasterizer/tests/test_fused_training.py). ``use_fused_training = False``
        turns it off."""
        return (self.use_fused_training and torch.is_grad_enabled()
                and "fused_training" in self.capabilities)

    def render_parts(self, parts: list[tuple[str, Optional[NodeOutput]]], camera: Camera, t: SceneTime,
                     sh_degree: int = 3, hidden: frozenset[str] = frozenset()) -> RenderResult:
        """Render node outputs (name, output or None), e.g. actors in edited states: the
        inference path when :meth:`fast_inference`, the fused training path when
        :meth:`fused_training`, else :meth:`assemble` + :meth:`composite`. A recorded
        camera sees them at its refined pose (:meth:`seen_from`; the native paths hand the
        rasterizer the move instead of moved copies)."""
        if self.fused_training() or self.fast_inference():
            moved = self.camera_poses.world_transform(camera, t) if self.camera_poses is not None else None
            return self._render_native(parts, camera, t, sh_degree, hidden, train=self.fused_training(), moved=moved)
        g, slices, outputs = self.assemble(self.seen_from(parts, camera, t), camera)
        return self.composite(g, slices, outputs, camera, t, sh_degree, hidden)

    def _render_native(self, parts: list[tuple[str, Optional[NodeOutput]]], camera: Camera, t: SceneTime,
                       sh_degree: int, hidden: frozenset[str], train: bool,
                       moved: Optional[tuple[torch.Tensor, torch.Tensor]] = None) -> RenderResult:
        """:meth:`render_parts` through the rasterizer's own raw-Gaussian path: node outputs
        go in as parts, uncopied (``rasterize_gaussians_train`` with autograd when ``train``,
        else ``rasterize_gaussians``), placed outputs box-local under their poses; the
        rasterizer culls to the view itself (``cull_to_view``) and ``num_gaussians`` counts
        the rows it kept. ``moved``: the camera-pose correction's world transform, applied
        by the rasterizer."""
        gs, placements, slices, outputs, start = [], [], [], {}, 0
        for name, out in parts:
            if out is None:
                continue
            n = out.num_gaussians
            if train or n:  # training keeps empty outputs for the regularisers
                outputs[name] = out
            if n == 0:
                continue
            # placed outputs are drawn box-local under their poses: no world copy
            placed = out.placement is not None
            gs.append(out.local if placed else out.gaussians)
            placements.append(out.placement if placed else None)
            slices.append(NodeSlice(name, start, start + n, out.rows))
            start += n
        if not gs:
            return self.composite(None, slices, outputs, camera, t, sh_degree, hidden)
        env = {n: m for n, m in self.environment_nodes().items() if n not in hidden}
        settings = RasterSettings(background=None if env else self._background)
        draw = self.rasterizer.rasterize_gaussians_train if train else self.rasterizer.rasterize_gaussians
        clock = time.perf_counter()
        out, kept = draw(gs, camera, sh_degree, settings, cull=self.method.cull_to_view, moved=moved,
                         placements=placements)
        timings = {"raster": time.perf_counter() - clock, **out.timings}
        clock = time.perf_counter()
        rgb, evaluated = self.finish_image(out.rgb, out.alpha, env, camera, t)
        timings["environment"] = time.perf_counter() - clock
        return RenderResult(rgb, out.depth, out.alpha, out.absgrad2d, out.radii, slices, kept, outputs, timings,
                            evaluated)

    def render_lidar(self, parts: list[tuple[Node, Optional[NodeOutput]]], rays, settings=None,
                     geometry_only: bool = False) -> LidarRender:
        """Render the world Gaussians of node outputs ``parts`` ((node, output or None), e.g.
        :meth:`omnire.runtime.Reconstruction.drawn`'s groups) as a LiDAR sees them along
        ``rays`` (:class:`~omnire.rasterization.LidarRays`, R rays): activated Gaussians with
        their activated LiDAR features as colours through the rasterizer's
        ``rasterize_lidar``, decoded per ray (:func:`omnire.lidarmodel.decode`). Rows of a
        node without features (an actor inserted from a run that learned none) take this
        scene's initial values. Environment nodes return nothing.

        ``geometry_only``: ignore learned features (and allow a scene that learned none): the
        range is rendered, intensity is NaN and the ray-drop probability is 1 - alpha (a ray
        returns what it meets, nothing else drops)."""
        if self.lidar_features is None and not geometry_only:
            raise UserError("this scene learned no LiDAR features: train it with --method.lidar.enabled on a "
                            "scene with LiDAR to render LiDAR")
        settings = LidarSettings() if settings is None else settings
        columns: dict[str, list[torch.Tensor]] = {"means": [], "quats": [], "scales": [], "opacities": [], "f": []}
        for node, out in parts:
            if out is None or out.num_gaussians == 0:
                continue
            g = out.gaussians
            if geometry_only:
                features = g.means.new_zeros(len(g), 1)
            else:
                features = node.lidar_features(out)
                if features is None:
                    features = self.lidar_features.initial(len(g), g.means.device, g.means.dtype)
            # only the Gaussians that can reach a ray: the same sweep and gradients at a
            # fraction of the projection's cost when the rays span part of the sphere
            keep = torch.nonzero(may_reach(g.means, g.scales, rays, settings.eps_deg2))[:, 0]
            if len(keep) == len(g):
                keep = None
            for key, value in (("means", g.means), ("quats", g.quats), ("scales", g.scales),
                               ("opacities", g.opacities), ("f", features)):
                columns[key].append(value if keep is None else value[keep])
        R = len(rays.azimuth_deg)
        if not columns["means"]:
            zeros = torch.zeros(R, device=self.device)
            light = None if rays.probe_range is None else torch.ones(R, device=self.device)
            return LidarRender(zeros, zeros.clone(), zeros.clone(), torch.ones(R, device=self.device), zeros.clone(),
                               probe_transmittance=light)
        cat = {k: torch.cat(v) for k, v in columns.items()}
        splats = Splats(cat["means"], cat["quats"], torch.exp(cat["scales"]), torch.sigmoid(cat["opacities"]),
                        activate(cat["f"]))
        out = self.rasterizer.rasterize_lidar(splats, rays, settings)
        if geometry_only:
            return LidarRender(out.range, out.median_range, torch.full_like(out.alpha, float("nan")),
                               (1.0 - out.alpha).clamp(0.0, 1.0), out.alpha, len(splats), out.probe_transmittance)
        intensity, drop = decode(out.features, out.alpha)
        return LidarRender(out.range, out.median_range, intensity, drop, out.alpha, len(splats),
                           out.probe_transmittance)

    def composite(self, g: Optional[Gaussians], slices: list[NodeSlice], outputs: dict[str, NodeOutput],
                  camera: Camera, t: SceneTime, sh_degree: int = 3, hidden: frozenset[str] = frozenset()
                  ) -> RenderResult:
        """Rasterize gathered Gaussians ``g`` (:meth:`gather` / :meth:`assemble`) through
        ``camera`` with SH bands up to ``sh_degree`` and composite the environment nodes not
        in ``hidden`` (at moment ``t``) under them."""
        env = {n: m for n, m in self.environment_nodes().items() if n not in hidden}
        background = None if env else self._background
        W, H = camera.width, camera.height
        if g is not None:
            splats = Splats(g.means, g.quats, g.activated_scales, g.activated_opacities,
                            g.colors(camera.center, sh_degree))
            out = self.rasterizer.rasterize(splats, camera, RasterSettings(background=background))
            rgb, depth, alpha, absgrad, radii = out.rgb, out.depth, out.alpha, out.absgrad2d, out.radii
            n = len(g)
        else:
            rgb = (background if background is not None else torch.zeros(3, device=self.device)).expand(H, W, 3)
            depth = torch.zeros(H, W, 1, device=self.device)
            alpha = torch.zeros(H, W, 1, device=self.device)
            absgrad = torch.zeros(0, 2, device=self.device)
            radii = torch.zeros(0, dtype=torch.int32, device=self.device)
            n = 0
        rgb, evaluated = self.finish_image(rgb, alpha, env, camera, t)
        return RenderResult(rgb, depth, alpha, absgrad, radii, slices, n, outputs, environment_pixels=evaluated)
