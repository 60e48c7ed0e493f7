"""The scene runtime: a reconstructed scene you can hold and render.

:class:`Reconstruction` is the scene data plus its scene graph (the nodes of a method) and a
rasterizer. It is built fresh for training (:meth:`Reconstruction.build`: scene preparation,
track assignment, data-driven initialisation) or loaded from a run directory
(:meth:`Reconstruction.from_run`: run.json + a checkpoint, without a trainer, an optimiser
or reading any training image), and renders any camera at any moment:
``render(camera, time) -> RenderResult``. The trainer holds one and adds optimisation;
evaluation, rendering, benchmarks, simulation, export and the viewer use its public methods
and never reach into its model.

What is drawn at a moment is asked in one way, :meth:`Reconstruction.drawn`: it yields one
:class:`Drawn` per group a node draws (every non-actor Gaussian node as recorded, per actor
node the actors as recorded, each edited actor alone in its edited state, then actors
inserted from other runs), each with its node, actor state and moment. Edits come from an
:class:`ActorEdits` (``omnire_sim.Simulation`` is one); without, the recording is drawn.
``render`` renders exactly those groups (:meth:`node_outputs` + :meth:`render_outputs`), so
rendering, the simulation, export and the viewer agree on what is there.

Example::

    recon = Reconstruction.from_run(Path("outputs/run"), load_plugins())
    view = recon.scene.views(recon.scene.test_frames)[0]
    image = recon.render(recon.camera(view).shifted((1.0, 0, 0)), recon.time(view.frame)).rgb  # (H, W, 3)
"""
from __future__ import annotations

import copy
import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from time import perf_counter
from typing import TYPE_CHECKING, Collection, Iterable, Iterator, Mapping, Optional, Protocol, Sequence

import numpy as np
import torch

from omnire.camera import Camera
from omnire.data.scene import SceneData, SceneTime, View
from omnire.model import RenderResult, SceneModel, enabled_node_specs
from omnire.nodes.actors import ActorNode, ActorState
from omnire.nodes.base import EnvironmentNode, Node, NodeOutput
from omnire.gaussians import Gaussians
from omnire.lidarmodel import LidarRender
from omnire.lidarsweep import SensorPath, SweepRays, sectors_of
from omnire.rasterization import Rasterizer, describe_paths, select_backend
from omnire.rundir import RunDirectory, RunInfo, find_checkpoint
from omnire.runconfig import TrainConfig, parse_train_args
from omnire.strategy import NodeSlice

if TYPE_CHECKING:
    from omnire.rasterization import LidarRays, LidarSettings

log = logging.getLogger("omnire.runtime")


class EditedActor(Protocol):
    """One actor an :class:`ActorEdits` draws itself: ``key`` (its track id, or an inserted
    actor's id), the node that draws it (``node_name`` of ``owner``, whose ``node``) and,
    unless ``removed``, its state at a moment."""

    key: str
    removed: bool
    node_name: str
    node: ActorNode
    owner: "Reconstruction"

    def state(self, seconds: float, time: SceneTime) -> Optional[tuple[ActorState, SceneTime]]:
        """(ActorState of one actor, the moment its node draws it at) at scene moment ``time``
        (``seconds`` since the log's first frame), or None when it is absent then."""
        ...


class ActorEdits(Protocol):
    """Edits of the actors a :class:`Reconstruction` draws (the simulation's resolved
    scenario implements it; the core does not depend on the simulation)."""

    def edited(self, node_name: str) -> Mapping[int, EditedActor]:
        """The actors of this run's node ``node_name`` drawn by the edits instead of as
        recorded, by instance index (removed ones included)."""
        ...

    def inserted(self) -> Iterable[EditedActor]:
        """Actors added to the scene (drawn by their own run's node), in drawing order."""
        ...


class Drawn:
    """One group a node draws at a moment (see the module docstring).

    Attributes:
        label: the part's name: the node name; ``<node>:<key>`` for an edited actor;
            ``insert:<key>`` for an inserted one.
        node_name, node, owner: the node drawing it (``owner``: the run it belongs to, another
            run for inserted actors).
        moment: the moment the node draws it at (an actor's own clock when edited).
        inserted: an actor from another run.
        recorded: the node's whole recording at ``moment``, drawn as the node draws itself.
    """

    def __init__(self, label: str, node_name: str, node: Node, owner: "Reconstruction", moment: SceneTime,
                 state: Optional[ActorState] = None, keys: Optional[tuple[str, ...]] = None,
                 recorded: bool = False, inserted: bool = False) -> None:
        self.label, self.node_name, self.node, self.owner, self.moment = label, node_name, node, owner, moment
        self.recorded, self.inserted = recorded, inserted
        self._state, self._keys = state, keys

    @property
    def is_actor(self) -> bool:
        return isinstance(self.node, ActorNode)

    @property
    def state(self) -> Optional[ActorState]:
        """The actors drawn (P of them: ids (P,), R (P, 3, 3), t (P, 3), body); None for a
        node without actors. Read from the node when the group is its recording."""
        if self._state is None and self.recorded and self.is_actor:
            self._state = self.node.state_at(self.moment)
        return self._state

    @property
    def keys(self) -> tuple[str, ...]:
        """(P,) the track / insert ids of :attr:`state`'s actors; () for a node without actors."""
        if self._keys is None:
            state = self.state
            self._keys = () if state is None else tuple(self.node.track_ids[i] for i in state.ids.tolist())
        return self._keys

    def output(self, camera: Optional[Camera] = None, step: Optional[int] = None) -> Optional[NodeOutput]:
        """The node's world-space Gaussians of this group (``camera``: what the node may skip
        as unseen; ``step``: the training step of a recording)."""
        if self.recorded or not self.is_actor:
            return self.node.gaussians_at(self.moment, camera, step)
        return self.node.gaussians_for(self.state, self.moment, camera)


class Reconstruction:
    """A scene and its scene graph, ready to render. See the module docstring.

    Attributes:
        scene: the :class:`SceneData`.
        model: the :class:`~omnire.model.SceneModel` (the core's; tools use the methods here).
        method: the method config.
        step: training steps behind the current state (0 for a fresh build); the one step
            counter of a run (the trainer advances it).
        schedule_step: where the training schedules stand (:mod:`omnire.schedule`): ``step``
            itself, unless a time budget set it apart (the trainer sets it then; checkpoints
            keep it). The SH degree of a render follows it.
        run_info, config, run_dir, checkpoint: the run it was loaded from
            (:meth:`from_run`); None when built fresh.
    """

    def __init__(self, scene: SceneData, model: SceneModel, method, step: int = 0, *,
                 run_info: Optional[RunInfo] = None, config: Optional[TrainConfig] = None,
                 run_dir: Optional[RunDirectory] = None, checkpoint: Optional[Path] = None) -> None:
        self.scene = scene
        self.model = model
        self.method = method
        self.step = step
        self._schedule_step: Optional[int] = None
        self.run_info = run_info
        self.config = config
        self.run_dir = run_dir
        self.checkpoint = checkpoint
        self.device = model.device
        # cameras as tensors on the device, converted once
        self._K = [torch.as_tensor(c.intrinsics, dtype=torch.float32, device=self.device) for c in scene.cameras]
        self._c2w = [torch.as_tensor(c.cam_to_world, dtype=torch.float32, device=self.device) for c in scene.cameras]
        self._side_by_side: Optional[ThreadPoolExecutor] = None  # render_cameras' workers, made at first use

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(cls, method, scene: SceneData, plugins, device: torch.device, images, seed: int = 0) -> "Reconstruction":
        """A new scene graph for ``scene``: the enabled node types prepare the scene (e.g.
        body poses), tracks are assigned to node types, nodes initialise from the data."""
        specs = enabled_node_specs(method, plugins.node_types)
        for name, spec in specs.items():
            if spec.prepare is not None:
                spec.prepare(scene, plugins, method.nodes[name])
        backend = select_backend(plugins, method.rasterizer, device)
        log.info(backend.describe())
        model = SceneModel(method, scene, specs, images, backend.rasterizer, device, seed=seed,
                           capabilities=backend.capabilities)
        return cls(scene, model, method)

    @classmethod
    def restore(cls, config: TrainConfig, scene: SceneData, plugins, device: torch.device, assignment: dict,
                state: dict, assign: bool = False, *, run_info: Optional[RunInfo] = None,
                run_dir: Optional[RunDirectory] = None, checkpoint: Optional[Path] = None) -> "Reconstruction":
        """The scene graph of a checkpoint ``state`` (with the recorded track ``assignment``):
        nodes are built empty, then filled from the state (``assign``: see :meth:`load_state`).
        ``run_info``, ``run_dir``, ``checkpoint``: where it was read from, if from a run."""
        specs = enabled_node_specs(config.method, plugins.node_types)
        backend = select_backend(plugins, config.method.rasterizer, device)
        model = SceneModel(config.method, scene, specs, None, backend.rasterizer, device, assignment=assignment,
                           restoring=True, capabilities=backend.capabilities)
        recon = cls(scene, model, config.method, run_info=run_info, config=config, run_dir=run_dir,
                    checkpoint=checkpoint)
        recon.load_state(state, assign=assign)
        return recon

    @classmethod
    def from_run(cls, run_dir: Path, plugins, checkpoint: Optional[Path] = None,
                 device: Optional[str] = None, read_only: bool = False) -> "Reconstruction":
        """Load a trained scene from a run directory (its newest intact checkpoint, or
        ``checkpoint``). Reads run.json and the scene's metadata; no training image.

        ``read_only`` (CPU): the model's tensors are memory-mapped from the checkpoint file
        and used in place, without gradients: peak memory about the parameters once (for
        export and viewing; not for training)."""
        run = RunDirectory(run_dir)
        info = run.read_info()
        config = parse_recorded_args(info, plugins)
        dev = torch.device("cpu" if read_only else (device or config.trainer.device))
        _, path, state = find_checkpoint(checkpoint or run.path, map_location=dev, mmap=read_only)
        scene = config.dataparser.setup().load()
        recon = cls.restore(config, scene, plugins, dev, info.node_assignment, state, assign=read_only,
                            run_info=info, run_dir=run, checkpoint=path)
        if read_only:
            recon.model.requires_grad_(False)
        return recon

    def snapshot(self) -> "Reconstruction":
        """A copy whose model tensors are independent of this one's and take no gradients
        (scene data, method, rasterizer and run record shared): e.g. a viewer showing a run
        while it trains."""
        model = self.model
        memo = {id(model.scene): model.scene, id(model.rasterizer): model.rasterizer, id(model.method): model.method}
        with torch.no_grad():
            copied = copy.deepcopy(model, memo)
        copied.requires_grad_(False)
        snapshot = Reconstruction(self.scene, copied, self.method, step=self.step, run_info=self.run_info,
                                  config=self.config, run_dir=self.run_dir, checkpoint=self.checkpoint)
        snapshot.schedule_step = self._schedule_step
        return snapshot

    @property
    def schedule_step(self) -> int:
        """Where the training schedules stand: :attr:`step`, unless set apart (a time budget)."""
        return self.step if self._schedule_step is None else self._schedule_step

    @schedule_step.setter
    def schedule_step(self, value: Optional[int]) -> None:
        """Set the schedule step apart from the step count (None: follow :attr:`step` again)."""
        self._schedule_step = None if value is None else int(value)

    # ------------------------------------------------------------------ state
    def load_state(self, state: dict, assign: bool = False) -> None:
        """Load a checkpoint's model state (Gaussian counts may differ from the current ones).
        ``assign``: adopt the state's tensors instead of copying them (e.g. memory-mapped ones)."""
        for name, node in self.model.nodes.items():
            node.prepare_load(state["model"], prefix=f"nodes.{name}.")
        if self.model.exposure is not None and "exposure.delta" not in state["model"]:
            self.model.exposure = None  # trained before exposure was learned: render without it
        if self.model.camera_poses is not None and "camera_poses.delta" not in state["model"]:
            self.model.camera_poses = None  # trained before pose refinement was learned: recorded poses
        self.model.load_state_dict(state["model"], assign=assign)
        self.step = int(state["step"])
        self.schedule_step = state.get("schedule_step")  # None: the step count (step budgets, older runs)

    # ------------------------------------------------------------------ queries
    @property
    def assignment(self) -> dict[str, list[str]]:
        """Track ids per node type."""
        return self.model.assignment

    @property
    def nodes(self) -> dict[str, Node]:
        """Every node by name, in drawing order."""
        return dict(self.model.nodes)

    def actor_nodes(self) -> dict[str, ActorNode]:
        """The nodes drawing actors (boxes under poses), by name."""
        return {n: m for n, m in self.model.nodes.items() if isinstance(m, ActorNode)}

    def gaussian_nodes(self) -> dict[str, Node]:
        """The nodes drawing Gaussians (every node but the environment ones), by name, in
        drawing order."""
        return self.model.gaussian_nodes()

    def environment_nodes(self) -> dict[str, EnvironmentNode]:
        """The nodes composited under the Gaussians (e.g. the sky), by name."""
        return self.model.environment_nodes()

    def find_actor(self, track: str) -> Optional[tuple[str, ActorNode, int]]:
        """(node name, node, instance index) of the actor with track id ``track``, or None
        (not in the scene, or drawn as part of the background)."""
        for name, node in self.actor_nodes().items():
            if track in node.track_ids:
                return name, node, node.track_ids.index(track)
        return None

    @property
    def scene_radius(self) -> float:
        """The scene's scale in metres (:func:`omnire.model.scene_radius`)."""
        return self.model.scene_radius

    @property
    def rasterizer(self) -> Rasterizer:
        """The rasterizer backend this scene renders with (omnire/rasterization.py's contract)."""
        return self.model.rasterizer

    @property
    def rasterizer_name(self) -> str:
        return self.model.rasterizer.name

    def rasterizer_paths(self) -> str:
        """Which path each optional rasterizer capability takes (one line)."""
        return describe_paths(self.model.capabilities)

    @property
    def use_fused_training(self) -> bool:
        """Whether renders with autograd take the rasterizer's fused training path when it
        declares one (:meth:`omnire.model.SceneModel.fused_training`); False for comparisons."""
        return self.model.use_fused_training

    @use_fused_training.setter
    def use_fused_training(self, value: bool) -> None:
        self.model.use_fused_training = bool(value)

    def num_gaussians(self) -> int:
        return self.model.num_gaussians()

    @property
    def renders_lidar(self) -> bool:
        """The scene learned LiDAR features (``--method.lidar.enabled`` on a scene with LiDAR),
        so :meth:`render_lidar` can render it."""
        return self.model.lidar_features is not None

    def sh_degree(self, step: Optional[int] = None) -> int:
        """SH bands switched on at schedule step ``step`` (default: the state's
        :attr:`schedule_step`, the step count unless a time budget set it apart)."""
        s = self.schedule_step if step is None else step
        return min(3, s // max(1, self.method.sh_degree_interval))

    def camera(self, view: View) -> Camera:
        """The recorded camera of ``view``."""
        cam = self.scene.cameras[view.camera]
        return Camera(self._K[view.camera], self._c2w[view.camera][view.frame], cam.width, cam.height, cam.name)

    def time(self, frame: float) -> SceneTime:
        """The moment of (possibly fractional) ``frame``."""
        return self.scene.time_of_frame(frame)

    def time_since_start(self, seconds: float) -> SceneTime:
        """The moment ``seconds`` after the log's first frame (clamped to the log)."""
        return self.scene.time_since_start(seconds)

    # ------------------------------------------------------------------ drawing
    def drawn(self, time: SceneTime, edits: Optional[ActorEdits] = None, only: Optional[Collection[str]] = None,
              hidden: Collection[str] = frozenset()) -> Iterator[Drawn]:
        """Every group drawn at scene moment ``time``, in drawing order: the Gaussian nodes in
        order (a node without actors as recorded; an actor node's recording, or with
        ``edits`` its unedited actors together and then each edited actor alone, removed
        ones left out), then the actors ``edits`` inserts. ``only``: just the actors with
        these keys (track / insert ids), no node without actors; ``hidden``: node names of
        this run not drawn."""
        seconds = time.seconds - float(self.scene.frame_timestamps[0])
        for name, node in self.model.gaussian_nodes().items():
            if name in hidden:
                continue
            if not isinstance(node, ActorNode):
                if only is None:
                    yield Drawn(name, name, node, self, time)
                continue
            edited = edits.edited(name) if edits is not None else {}
            if not edited and only is None:
                yield Drawn(name, name, node, self, time, recorded=True)
                continue
            state = node.state_at(time)
            keep = [k for k, i in enumerate(state.ids.tolist())
                    if i not in edited and (only is None or node.track_ids[i] in only)]
            if keep:
                if len(keep) < len(state.ids):
                    state = state.select(torch.tensor(keep, dtype=torch.long, device=state.ids.device))
                yield Drawn(name, name, node, self, time, state)
            for actor in edited.values():
                if not actor.removed and (only is None or actor.key in only):
                    yield from _edited(actor, f"{name}:{actor.key}", seconds, time, inserted=False)
        for actor in edits.inserted() if edits is not None else ():
            if not actor.removed and (only is None or actor.key in only):
                yield from _edited(actor, f"insert:{actor.key}", seconds, time, inserted=True)

    def gather(self, camera: Optional[Camera], time: SceneTime
               ) -> tuple[Optional[Gaussians], list[NodeSlice], dict[str, NodeOutput]]:
        """The recorded scene's world-space Gaussians at ``time`` as a render draws them
        (:meth:`~omnire.model.SceneModel.gather`): ``(g, slices, outputs)`` with ``g`` the N
        Gaussians of every Gaussian node concatenated (culled to ``camera`` when the method
        culls and a camera is given, placed as ``camera`` sees them at its refined pose), or
        None when nothing is present; ``slices`` one :class:`~omnire.strategy.NodeSlice` per
        node, rows ``start:end`` of ``g`` coming from that node's rows ``rows`` ((end - start,)
        long, or None for its first end - start rows); ``outputs`` each node's output."""
        return self.model.gather(camera, time)

    def node_outputs(self, drawn: Iterable[Drawn], camera: Optional[Camera], time: SceneTime,
                     step: Optional[int] = None) -> list[tuple[str, Optional[NodeOutput]]]:
        """(label, node output or None) of each group of ``drawn`` at scene moment ``time``,
        each node told what ``camera`` sees (:meth:`~omnire.model.SceneModel.node_camera`)."""
        seen_by = self.model.node_camera(camera, time)
        return [(d.label, d.output(seen_by, step)) for d in drawn]

    def render_outputs(self, parts: list[tuple[str, Optional[NodeOutput]]], camera: Camera, time: SceneTime,
                       step: Optional[int] = None, sh_degree: Optional[int] = None,
                       hidden: Collection[str] = frozenset()) -> RenderResult:
        """Rasterize node outputs ``parts`` (:meth:`node_outputs`) through ``camera`` and
        composite the environment nodes not in ``hidden`` at ``time`` under them
        (:meth:`~omnire.model.SceneModel.render_parts`: the rasterizer's declared paths)."""
        degree = self.sh_degree(step) if sh_degree is None else sh_degree
        return self.model.render_parts(parts, camera, time, degree, frozenset(hidden))

    def render(self, camera: Camera, time: SceneTime, step: Optional[int] = None,
               hidden: frozenset[str] = frozenset(), sh_degree: Optional[int] = None,
               edits: Optional[ActorEdits] = None, only: Optional[Collection[str]] = None) -> RenderResult:
        """Render what :meth:`drawn` yields at ``time`` through ``camera``. ``step``: the
        schedule step of training (:mod:`omnire.schedule`; for warm-up schedules; None renders
        the trained model); ``hidden``:
        node names not drawn; ``edits``, ``only``: as :meth:`drawn` (with ``only`` the
        environment is left out too). The result's ``timings`` add the node evaluation
        (``nodes``) to the rasterizer path's."""
        clock = perf_counter()
        parts = self.node_outputs(self.drawn(time, edits, only, hidden), camera, time, step)
        seconds = perf_counter() - clock
        if only is not None:
            hidden = frozenset(hidden) | frozenset(self.environment_nodes())
        result = self.render_outputs(parts, camera, time, step, sh_degree, hidden)
        result.timings["nodes"] = seconds
        return result

    def render_cameras(self, cameras: Sequence[Camera], time: SceneTime, **options) -> list[RenderResult]:
        """:meth:`render` (with ``options``) through each of ``cameras`` at one ``time``: a
        rig's cameras, the same results as one at a time.

        Without autograd and with two torch threads or more, the first camera renders with
        every thread (leaving the moment's actor outputs cached for the others) and the rest
        then render side by side, one thread each: on few cores whole renders side by side
        scale better than the threads of one render, whose small torch operations wait on each
        other. Grad mode is per thread, so the workers turn it off too."""
        cameras = list(cameras)
        threads = torch.get_num_threads()
        if len(cameras) < 2 or threads < 2 or torch.is_grad_enabled():
            return [self.render(c, time, **options) for c in cameras]
        first = self.render(cameras[0], time, **options)
        if self._side_by_side is None:
            self._side_by_side = ThreadPoolExecutor(threads, thread_name_prefix="omnire-render")

        def render_without_grad(camera: Camera) -> RenderResult:
            with torch.no_grad():
                return self.render(camera, time, **options)

        torch.set_num_threads(1)
        try:
            return [first, *self._side_by_side.map(render_without_grad, cameras[1:])]
        finally:
            torch.set_num_threads(threads)

    def render_lidar(self, rays: LidarRays, time: SceneTime, step: Optional[int] = None,
                     hidden: Collection[str] = frozenset(), edits: Optional[ActorEdits] = None,
                     only: Optional[Collection[str]] = None, settings: Optional[LidarSettings] = None,
                     geometry_only: bool = False) -> LidarRender:
        """Render LiDAR ``rays`` (one sensor pose, R rays) at scene moment ``time``: what
        :meth:`drawn` yields (``edits``, ``only``, ``hidden`` as there), activated, with the
        learned LiDAR features as colours, through the rasterizer's ``rasterize_lidar``
        (:meth:`omnire.model.SceneModel.render_lidar`). Per ray: range, median range,
        intensity, ray-drop probability (:class:`~omnire.lidarmodel.LidarRender`).
        ``geometry_only``: range alone, also for a scene that learned no LiDAR features
        (intensity NaN, ray drop 1 - alpha; :meth:`omnire.model.SceneModel.render_lidar`)."""
        drawn = list(self.drawn(time, edits, only, hidden))
        outputs = self.node_outputs(drawn, None, time, step)
        return self.model.render_lidar([(d.node, out) for d, (_, out) in zip(drawn, outputs)], rays, settings,
                                       geometry_only)

    def sweep_actor_moment(self, sweep: SweepRays, sector_time: float) -> SceneTime:
        """The moment whose actors the rays of ``sweep`` fired around ``sector_time`` (log
        seconds) meet: that time itself when the scene's boxes hold their actors at the
        frames' timestamps; the sweep's end (its last ray's time, a recorded frame's
        timestamp) when they hold them where the sweep saw them (``SceneData.box_timing``
        ``"sweep"``), so that every sector meets each actor where its box was drawn."""
        seconds = sector_time
        if self.scene.box_timing == "sweep" and len(sweep):
            seconds = float(sweep.times.max())
        return self.time_since_start(seconds - float(self.scene.frame_timestamps[0]))

    def render_sweep(self, sweep: SweepRays, path: SensorPath, sectors: int = 1, step: Optional[int] = None,
                     hidden: Collection[str] = frozenset(), edits: Optional[ActorEdits] = None,
                     settings: Optional[LidarSettings] = None, probe_range: Optional[np.ndarray] = None
                     ) -> LidarRender:
        """Render a sweep's rays (:class:`~omnire.lidarsweep.SweepRays`, in the order given)
        from the sensor poses ``path`` gives at their times, in ``sectors`` equal time spans
        (rolling shutter: each span's rays are cast from the sensor at the span's middle time,
        :func:`~omnire.lidarsweep.sectors_of`, and meet the actors of
        :meth:`sweep_actor_moment`); with ``probe_range`` (R,) metres, the transmittance left
        there on each ray too (``LidarRender.probe_transmittance``)."""
        parts, order = [], []
        for sector in sectors_of(sweep, path, sectors, self.device, probe_range=probe_range):
            parts.append(self.render_lidar(sector.rays, self.sweep_actor_moment(sweep, sector.time), step, hidden,
                                           edits, settings=settings))
            order.append(sector.index)
        if not parts:
            empty = torch.zeros(0, device=self.device)
            return LidarRender(empty, empty, empty, empty, empty)
        return LidarRender.cat(parts, torch.cat(order))

    def render_view(self, view: View, step: Optional[int] = None) -> RenderResult:
        """Render the recorded camera and moment of ``view``."""
        return self.render(self.camera(view), self.time(view.frame), step=step)


def _edited(actor: EditedActor, label: str, seconds: float, time: SceneTime, inserted: bool) -> Iterator[Drawn]:
    """The group of one edited actor at scene moment ``time``, if present then."""
    got = actor.state(seconds, time)
    if got is not None:
        yield Drawn(label, actor.node_name, actor.node, actor.owner, got[1], got[0], (actor.key,), inserted=inserted)


def parse_recorded_args(info: RunInfo, plugins) -> TrainConfig:
    """The :class:`TrainConfig` of a recorded run. Relative paths of runs recorded before
    paths were stored absolute are taken relative to the recorded working directory."""
    config = parse_train_args(list(info.argv), plugins)
    config.trainer.resume = None
    cwd = info.extra.get("cwd")
    if cwd and Path(cwd).is_dir():
        from omnire.runconfig import absolute_argv

        argv = absolute_argv(list(info.argv), config, Path(cwd))
        if argv != info.argv:
            config = parse_train_args(argv, plugins)
            config.trainer.resume = None
    return config

