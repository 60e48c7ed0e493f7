"""The scene runtime: a reconstructed scene you can hold and render.

:class:`Reconstruction` is the scene data plus its scene graph (the nodes of a method) and a
rasterizer. It is built fresh for training (:meth:`Reconstruction.build`: scene preparation,
track assignment, data-driven initialisation) or loaded from a run directory
(:meth:`Reconstruction.from_run`: run.json + a checkpoint, without a trainer, an optimiser
or reading any training image), and renders any camera at any moment:
``render(camera, time) -> RenderResult``. The trainer holds one and adds optimisation;
evaluation, rendering, benchmarks, simulation, export and the viewer use its public methods.

Example::

    recon = Reconstruction.from_run(Path("outputs/run"), load_plugins())
    view = recon.scene.views(recon.scene.test_frames)[0]
    image = recon.render(recon.camera(view).shifted((1.0, 0, 0)), recon.time(view.frame)).rgb  # (H, W, 3)
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from omnire.camera import Camera
from omnire.data.scene import SceneData, SceneTime, View
from omnire.model import RenderResult, SceneModel, enabled_node_specs
from omnire.rasterization import select_rasterizer
from omnire.rundir import RunDirectory, RunInfo, find_checkpoint
from omnire.runconfig import TrainConfig, parse_train_args


class Reconstruction:
    """A scene and its scene graph, ready to render. See the module docstring.

    Attributes:
        scene: the :class:`SceneData`.
        model: the :class:`~omnire.model.SceneModel` (nodes by name in ``model.nodes``).
        method: the method config.
        step: training steps behind the current state (0 for a fresh build).
    """

    def __init__(self, scene: SceneData, model: SceneModel, method, step: int = 0) -> None:
        self.scene = scene
        self.model = model
        self.method = method
        self.step = step
        self.device = model.device
        # cameras as tensors on the device, converted once
        self._K = [torch.as_tensor(c.intrinsics, dtype=torch.float32, device=self.device) for c in scene.cameras]
        self._c2w = [torch.as_tensor(c.cam_to_world, dtype=torch.float32, device=self.device) for c in scene.cameras]

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(cls, method, scene: SceneData, plugins, device: torch.device, images, seed: int = 0) -> "Reconstruction":
        """A new scene graph for ``scene``: the enabled node types prepare the scene (e.g.
        body poses), tracks are assigned to node types, nodes initialise from the data."""
        specs = enabled_node_specs(method, plugins.node_types)
        for name, spec in specs.items():
            if spec.prepare is not None:
                spec.prepare(scene, plugins, method.nodes[name])
        rasterizer = select_rasterizer(plugins, method.rasterizer, device)
        model = SceneModel(method, scene, specs, images, rasterizer, device, seed=seed)
        return cls(scene, model, method)

    @classmethod
    def restore(cls, config: TrainConfig, scene: SceneData, plugins, device: torch.device, assignment: dict,
                state: dict, assign: bool = False) -> "Reconstruction":
        """The scene graph of a checkpoint ``state`` (with the recorded track ``assignment``):
        nodes are built empty, then filled from the state (``assign``: see :meth:`load_state`)."""
        specs = enabled_node_specs(config.method, plugins.node_types)
        rasterizer = select_rasterizer(plugins, config.method.rasterizer, device)
        model = SceneModel(config.method, scene, specs, None, rasterizer, device, assignment=assignment,
                           restoring=True)
        recon = cls(scene, model, config.method)
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
        recon = cls.restore(config, scene, plugins, dev, info.node_assignment, state, assign=read_only)
        if read_only:
            recon.model.requires_grad_(False)
        recon.run_info, recon.config, recon.run_dir, recon.checkpoint = info, config, run, path
        return recon

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

    # ------------------------------------------------------------------ queries
    @property
    def assignment(self) -> dict[str, list[str]]:
        """Track ids per node type."""
        return self.model.assignment

    def num_gaussians(self) -> int:
        return self.model.num_gaussians()

    def sh_degree(self, step: Optional[int] = None) -> int:
        """SH bands switched on after ``step`` training steps (default: the state's step)."""
        s = self.step if step is None else step
        return min(3, s // max(1, self.method.sh_degree_interval))

    def camera(self, view: View) -> Camera:
        """The recorded camera of ``view``."""
        cam = self.scene.cameras[view.camera]
        return Camera(self._K[view.camera], self._c2w[view.camera][view.frame], cam.width, cam.height, cam.name)

    def time(self, frame: float) -> SceneTime:
        """The moment of (possibly fractional) ``frame``."""
        return self.scene.time_of_frame(frame)

    def render(self, camera: Camera, time: SceneTime, step: Optional[int] = None,
               hidden: frozenset[str] = frozenset(), sh_degree: Optional[int] = None) -> RenderResult:
        """Render the scene at ``time`` through ``camera``. ``step``: the training step (for
        warm-up schedules; None renders the trained model); ``hidden``: node names not drawn."""
        degree = self.sh_degree(step) if sh_degree is None else sh_degree
        return self.model.render(camera, time, degree, step=step, hidden=hidden)

    def render_view(self, view: View, step: Optional[int] = None) -> RenderResult:
        """Render the recorded camera and moment of ``view``."""
        return self.render(self.camera(view), self.time(view.frame), step=step)


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

