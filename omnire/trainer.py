"""Training: a :class:`~omnire.runtime.Reconstruction` plus optimisation, evaluation and
checkpoints, in a run directory (:mod:`omnire.rundir`).

A training step runs through the named stages of :data:`STEP_STAGES` in order (one method
each, ``stage_<name>``, passing a :class:`StepState` along): ``omnire bench step`` times the
very step training takes, stage by stage. The step counter is the reconstruction's
(``Trainer.step`` reads ``recon.step``; the ``optimizer`` stage advances it).

Every schedule (learning rates, densification, SH bands, coarse-to-fine, node warm-ups)
reads the schedule step of :mod:`omnire.schedule`: the step counter for a step budget, the
clock's for a time budget (``--trainer.max-seconds``), which the ``densify`` stage advances
(``recon.schedule_step``).

Checkpoints hold the model, optimiser moments, densification state and every RNG state, so
a resumed run continues exactly like an uninterrupted one. Ctrl-C (SIGINT) or SIGTERM
writes a checkpoint at the current step and stops with :class:`TrainingInterrupted`.
"""
from __future__ import annotations

import dataclasses
import io
import json
import logging
import math
import signal
import time
from pathlib import Path
from typing import Callable, Optional

import torch

from omnire.allocator import retain_freed_memory
from omnire.camera import Camera
from omnire.config import to_dict
from omnire.data.scene import SceneData, SceneTime, View
from omnire.errors import ConfigError, UserError
from omnire.io.atomic import atomic_write_bytes, atomic_write_text
from omnire.lidartraining import LidarTraining
from omnire.lidarsweep import aimed_from_sectors
from omnire.losses import LossContext, masked_mean, ssim_map
from omnire.model import RenderResult
from omnire.nodes.base import NodeOutput
from omnire.shbands import fit_sh_bands
from omnire.observations import Observations
from omnire.contribution import node_contributions, prune_nodes
from omnire.resolution import downscale_factor
from omnire.optim import Optimizers
from omnire.rundir import RunDirectory, RunDirectoryError, RunInfo, find_checkpoint, step_of
from omnire.runconfig import TrainConfig, TrainerConfig, absolute_argv
from omnire.runtime import Reconstruction, parse_recorded_args
from omnire.schedule import Schedule
from omnire.strategy import AbsGradStrategy

__all__ = ["STEP_STAGES", "StepState", "TrainConfig", "Trainer", "TrainerConfig", "TrainingError",
           "TrainingInterrupted"]

log = logging.getLogger("omnire.trainer")

DIVERGENCE_PSNR = 12.0
"""Training PSNR (dB, over the last logged window) below which a run is reported as diverged."""


class TrainingError(UserError):
    """Training cannot continue (non-finite loss or parameters); nothing bad was saved."""


class TrainingInterrupted(UserError):
    """Training was stopped by a signal; a checkpoint of the current step was written. The
    CLI exits with 128 + the signal number (130 for Ctrl-C, 143 for SIGTERM)."""

    def __init__(self, message: str, signum: int) -> None:
        super().__init__(message)
        self.signum = signum


STEP_STAGES: tuple[str, ...] = ("prepare", "nodes", "render", "lidar", "loss", "backward", "densify_stats",
                                "optimizer", "densify")
"""The stages of one training step, in order (each is ``Trainer.stage_<name>``):

- ``prepare``: the step's schedule step (:mod:`omnire.schedule`), the SH bands stored up to
  its degree, the view's camera at its resolution and its moment;
- ``nodes``: every Gaussian node's output at the moment (``Reconstruction.drawn`` +
  ``node_outputs``);
- ``render``: rasterizer forward and environment (``Reconstruction.render_outputs``);
- ``lidar``: with ``--method.lidar.enabled``, every ``lidar.every`` steps, a training frame's
  sweep (``lidar.rays_per_step`` of its rays) rendered (``Reconstruction.render_sweep``) and
  its loss terms (omnire/lidarloss.py); nothing otherwise;
- ``loss``: loss terms and node regularisers, their sum, and the step's statistics;
- ``backward``: ``loss.backward()`` (rasterizer backward, autograd of nodes and losses);
- ``densify_stats``: the AbsGrad statistics (:meth:`AbsGradStrategy.accumulate`);
- ``optimizer``: the optimisers' step and ``zero_grad``; the step counter advances;
- ``densify``: the schedule step reached (the step count, or the clock's on a time budget);
  densification and pruning when the schedule says so (:meth:`AbsGradStrategy.step`).
"""


@dataclasses.dataclass
class StepState:
    """What one training step carries from stage to stage (filled in stage order)."""

    view: View
    schedule_step: int = 0
    factor: int = 1
    camera: Optional[Camera] = None
    time: Optional[SceneTime] = None
    parts: list[tuple[str, Optional[NodeOutput]]] = dataclasses.field(default_factory=list)
    result: Optional[RenderResult] = None
    context: Optional[LossContext] = None
    terms: dict[str, torch.Tensor] = dataclasses.field(default_factory=dict)
    lidar_terms: dict[str, torch.Tensor] = dataclasses.field(default_factory=dict)
    loss: Optional[torch.Tensor] = None
    stats: dict[str, float] = dataclasses.field(default_factory=dict)


def psnr_from_mse(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


class _RecordBuffer(logging.Handler):
    """Keeps log records emitted before the run's log file exists."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


class Trainer:
    """Trains ``config`` on ``scene`` (default: parsed by the config's dataparser).

    With ``persist=False`` nothing is written (benchmarks step a trainer in memory); otherwise
    the run directory is created (refused when it already holds a run) or, with
    ``--trainer.resume``, reopened and continued from its newest intact checkpoint.
    """

    def __init__(self, config: TrainConfig, plugins, argv: Optional[list[str]] = None,
                 scene: Optional[SceneData] = None, persist: bool = True) -> None:
        self.config = config
        self.plugins = plugins
        tc = config.trainer
        if tc.threads > 0:
            torch.set_num_threads(tc.threads)
        self.device = torch.device(tc.device)
        torch.manual_seed(tc.seed)
        self.argv = list(argv) if argv is not None else None
        self.persist = persist
        for name in tc.observers:
            plugins.train_observers.get(name)  # an unknown observer fails before any work
        resume_state = None
        self.run: Optional[RunDirectory] = None
        if persist:
            self.run, resume_state = self._open_run_directory(scene)
        buffer = _RecordBuffer()
        logging.getLogger("omnire").addHandler(buffer)
        logging.getLogger("omnire").setLevel(logging.INFO)
        if tc.retain_freed_memory and not retain_freed_memory():  # logged now that the log is set up
            log.info("--trainer.retain-freed-memory: not glibc; the allocator is left as it is")
        try:
            self.scene = scene if scene is not None else config.dataparser.setup().load()
            self.observations = Observations(self.scene, self.device)
            self.recon = Reconstruction.build(config.method, self.scene, plugins, self.device,
                                              self.observations.images, seed=tc.seed)
        finally:
            logging.getLogger("omnire").removeHandler(buffer)
        self._early_records = buffer.records
        self.losses = {}
        for name, weight in config.method.loss_weights.items():
            if weight != 0:
                self.losses[name] = (plugins.losses.get(name).fn, weight)
        self.model = self.recon.model
        self.schedule = Schedule.of(tc.max_steps, tc.max_seconds)
        self.optimizers = Optimizers(self.model.optimizable(), self.schedule.steps)
        self.strategy = AbsGradStrategy(config.method.densify, self.model.scene_radius, self.schedule.steps)
        self.densify_stop: Optional[dict] = None  # where growth stopped: step, schedule_step, train_seconds
        # sky masks only feed the opacity loss, which only means something with a sky node
        self.use_sky_masks = bool(self.model.environment_nodes()) and "opacity" in self.losses
        self.sampler = torch.Generator().manual_seed(tc.seed + 1)
        self.train_views = self.scene.views(self.scene.train_frames)
        self.test_views = self.scene.views(self.scene.test_frames)
        self.train_seconds = 0.0
        self._step_started = time.perf_counter()  # the current step's start (the schedule's clock)
        self.lidar = (LidarTraining(self.recon, tc.seed + 2, self.config.method.lidar.probe_edge_jump)
                      if self.model.lidar_features is not None else None)
        self._lidar_baselines: Optional[dict] = None  # the held-out sweeps' baselines, at the first evaluation
        self._sh_bands_degree: Optional[int] = None  # the degree fit_sh_bands last stored bands for
        self.observers: list = []
        self._stop_signal: Optional[int] = None
        if resume_state is not None:
            self.load_state(resume_state)
            self.run.truncate_metrics(self.step)
        elif self.schedule.timed:
            self.recon.schedule_step = self.schedule.position(self.step, self.train_seconds)

    # ------------------------------------------------------------------ run directory
    def _open_run_directory(self, scene: Optional[SceneData]) -> tuple[RunDirectory, Optional[dict]]:
        tc = self.config.trainer
        if tc.resume is None:
            name = tc.run_name or (f"{scene.name if scene is not None else self.config.dataparser_name}-"
                                   f"{self.config.method_name}-{time.strftime('%Y%m%d-%H%M%S')}")
            run = RunDirectory(Path(tc.output_dir) / name)
            run.create()
            return run, None
        source, ckpt, state = find_checkpoint(tc.resume, map_location=self.device)
        self.check_run_matches(source.read_info())
        source.remove_temporary_files()
        log.info("resuming from %s (step %s)", ckpt, step_of(ckpt))
        if tc.run_name is not None and RunDirectory(Path(tc.output_dir) / tc.run_name).path != source.path:
            # a branch: a new run directory that starts from the checkpoint
            run = RunDirectory(Path(tc.output_dir) / tc.run_name)
            run.create()
            return run, state
        return source, state

    def check_run_matches(self, info: RunInfo) -> None:
        """Refuse to continue a run with another method, method settings or data selection."""
        mine = self.config
        if mine.method_name != info.method or mine.dataparser_name != info.dataparser:
            raise ConfigError(f"--trainer.resume: the run trained {info.method} on {info.dataparser}; "
                              f"this command asks for {mine.method_name} on {mine.dataparser_name}")
        recorded = info.extra.get("settings")
        if recorded is None and info.argv:  # runs recorded before settings were stored
            theirs = parse_recorded_args(info, self.plugins)
            recorded = {"method": _comparable(theirs.method), "dataparser": _comparable(theirs.dataparser)}
        if recorded is None:
            return
        then = Path(info.extra.get("cwd") or Path.cwd())  # the recorded settings' relative paths are against it
        for key, what, config in (("dataparser", "data selection (dataparser flags)", mine.dataparser),
                                  ("method", "method settings (--method.* flags)", mine.method)):
            da, db = _comparable(config), recorded.get(key, {})
            # settings the recorded run did not have yet (added to omnire since) are not compared
            changed = sorted(k for k in set(da) | set(db) if k in db and not _same_setting(da.get(k), db.get(k), then))
            if changed:
                raise ConfigError(f"--trainer.resume: the {what} differ from the recorded run's: "
                                  + ", ".join(f"{k}: {db.get(k)!r} -> {da.get(k)!r}" for k in changed[:6]))

    def write_run_info(self, schedule: Optional[dict] = None) -> None:
        """Write run.json; ``schedule``: what :meth:`schedule_record` says (default: the plan)."""
        if self.run is None:
            return
        cwd = Path.cwd()
        argv = absolute_argv(self.argv, self.config, cwd) if self.argv is not None else []
        info = RunInfo(argv, self.config.method_name, self.config.dataparser_name, self.recon.assignment, {
            "cwd": str(cwd),
            "rasterizer": self.model.rasterizer.name,
            "scene": self.scene.name,
            "attribution": self.scene.attribution,
            "plugins": [[n, p.distribution, p.version] for n, p in self.plugins.loaded],
            "settings": {"method": _comparable(self.config.method),
                         "dataparser": _comparable(self.config.dataparser)},
            "schedule": schedule if schedule is not None else self.schedule_plan(),
        })
        atomic_write_text(self.run.info_path, info.to_json())

    @property
    def step(self) -> int:
        """Training steps taken: the reconstruction's counter (the one owner)."""
        return self.recon.step

    @property
    def run_dir(self) -> Optional[Path]:
        return None if self.run is None else self.run.path

    def schedule_plan(self) -> dict:
        """The schedule the run follows: :meth:`Schedule.describe` and the schedule step where
        densification stops growing."""
        return {**self.schedule.describe(), "densify_stop_schedule_step": self.strategy.refine_stop}

    def schedule_record(self) -> dict:
        """The schedule as run so far: the plan, the steps, training seconds and schedule step
        reached, where densification stopped growing (None: not yet) and every learning rate
        of the last step."""
        return {**self.schedule_plan(), "steps": self.step, "train_seconds": self.train_seconds,
                "schedule_step": self.recon.schedule_step, "densify_stopped": self.densify_stop,
                "final_lr": self.optimizers.learning_rates()}

    def sh_degree(self) -> int:
        return self.recon.sh_degree()

    def fit_sh_bands(self, discard_unused: bool = False) -> dict[str, tuple[int, int]]:
        """Store the nodes' SH bands up to the current degree (omnire/shbands.py): columns
        appended when the degree rises, unused zero columns dropped. Returns the nodes changed."""
        degree = self.sh_degree()
        if degree == self._sh_bands_degree and not discard_unused:
            return {}
        changed = fit_sh_bands(self.model.gaussian_nodes(), self.optimizers, degree, discard_unused)
        self._sh_bands_degree = degree
        return changed

    @torch.no_grad()
    def keep_gaussian_rows(self, node_name: str, keep: torch.Tensor) -> tuple[int, int]:
        """Keep only the Gaussians ``keep`` ((N,) bool over the rows of Gaussian node
        ``node_name``) and drop the rest: parameters, buffers and Adam moments are cut
        together, the node's row order is restored and its densification statistics are
        dropped, so training continues from the result. Returns (count before, count after)."""
        nodes = self.recon.gaussian_nodes()
        if node_name not in nodes:
            raise ValueError(f"node {node_name!r}: expected one of the Gaussian nodes {sorted(nodes)}")
        node = nodes[node_name]
        before = node.num_gaussians
        if keep.dtype != torch.bool or tuple(keep.shape) != (before,):
            raise ValueError(f"keep: {keep.dtype} of shape {tuple(keep.shape)}, "
                             f"expected torch.bool of shape ({before},)")
        self.optimizers.replace_gaussian_rows(node_name, node, lambda k, t: t[keep], lambda k, s: s[keep])
        self.strategy.rows_changed(node_name, node, self.optimizers)
        return before, node.num_gaussians

    def contribution_sources(self) -> int:
        """How many renders :meth:`training_contributions` makes: training views, and training
        sweeps when the run learns LiDAR."""
        return len(self.train_views) + (0 if self.lidar is None else len(self.lidar.frames))

    def training_contributions(self, progress: Optional[Callable[[], None]] = None) -> dict[str, torch.Tensor]:
        """Per Gaussian node, the (N_node,) contribution of each Gaussian to what the run trains
        on (:func:`omnire.contribution.node_contributions`): the training views and, when the
        run learns LiDAR, the training sweeps whole (each as one time sector, aimed from the
        sensor at its middle time). ``progress`` is called after each render."""
        # one sector (the sweep at its middle time): on the demo cut's LiDAR run (325k Gaussians,
        # 33 sweeps) the kept 40% agree with four sectors' on 99.1-99.8% of each node's rows,
        # in 23 s instead of 49 s
        sweeps = [] if self.lidar is None else [aimed_from_sectors(self.lidar.sweep(int(f)), self.lidar.path, 1)
                                                for f in self.lidar.frames]
        return node_contributions(self.recon, self.train_views, progress, sweeps=sweeps,
                                  path=None if self.lidar is None else self.lidar.path, sectors=1)

    def prune_after_growth(self) -> dict:
        """When growth has stopped: keep ``densify.keep_after_growth`` of each node's Gaussians,
        by :meth:`training_contributions` (nothing when the fraction is 1). Returns what the
        run's ``densify_stop`` record keeps: the counts before and after and the seconds taken."""
        fraction = self.config.method.densify.keep_after_growth
        if fraction >= 1.0:
            return {}
        start = time.perf_counter()
        counts = prune_nodes(self, self.training_contributions(), fraction)
        seconds = time.perf_counter() - start
        before, after = (sum(c[i] for c in counts.values()) for i in (0, 1))
        log.info("growth stopped: kept %d of %d Gaussians by their contribution to %d training renders (%.1f s)",
                 after, before, self.contribution_sources(), seconds)
        return {"pruned": {name: list(c) for name, c in counts.items()}, "prune_seconds": seconds}

    # ------------------------------------------------------------------ training
    def loss_context(self, view: View, result, factor: int = 1) -> LossContext:
        """What the losses compare ``result`` (rendered at 1 / ``factor`` resolution) with."""
        obs = self.observations
        lidar = obs.lidar(view, factor) if "depth" in self.losses else None
        weight = self.config.method.dynamic_pixel_weight
        pixel_weights = None
        if weight != 1.0 and self.scene.tracks:
            pixel_weights = 1.0 + (weight - 1.0) * obs.dynamic_mask(view, "all", factor)
        return LossContext(
            rgb=result.rgb, depth=result.depth, alpha=result.alpha, target=obs.image(view, factor),
            pixel_weights=pixel_weights,
            lidar_pixels=None if lidar is None else lidar[0], lidar_depth=None if lidar is None else lidar[1],
            sky_mask=obs.sky_mask(view, factor) if self.use_sky_masks else None,
            sky_trusted=obs.sky_trusted(view, factor) if self.use_sky_masks else None,
            scene_pixels=obs.scene_pixels(view, factor),
            step=self.recon.schedule_step,
            ssim=self.model.rasterizer.ssim_map if "ssim" in self.model.capabilities else ssim_map,
        )

    def resolution_factor(self, step: Optional[int] = None) -> int:
        """Training images are rendered at 1 / this of their resolution at schedule step
        ``step`` (default: the current one); see :mod:`omnire.resolution`."""
        m = self.config.method
        return downscale_factor(self.recon.schedule_step if step is None else step, m.num_downscales,
                                m.resolution_schedule)

    def sample_view(self) -> View:
        """The next training view (uniform over the training views, seeded)."""
        i = int(torch.randint(len(self.train_views), (1,), generator=self.sampler))
        return self.train_views[i]

    def loss_terms(self, ctx: LossContext, result, camera: Camera, t: SceneTime) -> dict[str, torch.Tensor]:
        """The weighted loss terms of one view (``camera`` at moment ``t``) rendered as
        ``result``: the method's losses on ``ctx``, the node regularisers of the result's
        outputs, and the penalties on the view's exposure and camera-pose corrections when
        those are learned."""
        terms: dict[str, torch.Tensor] = {}
        for name, (fn, weight) in self.losses.items():
            value = fn(ctx)
            if value is not None:
                terms[name] = weight * value
        reg_w = self.config.method.regularization_weights
        for node_name, output in result.outputs.items():
            for name, value in self.model.nodes[node_name].regularization(output).items():
                if reg_w.get(name, 0.0) != 0.0:
                    terms[name] = reg_w[name] * value
        for name, learned, weight in (("exposure", self.model.exposure, self.config.method.exposure_weight),
                                      ("camera_pose", self.model.camera_poses, self.config.method.camera_pose_weight)):
            value = None if learned is None else learned.regularization(camera.name, t)
            if value is not None:
                terms[name] = weight * value
        return terms

    def train_step(self, view: Optional[View] = None,
                   on_stage: Optional[Callable[[str], None]] = None) -> dict[str, float]:
        """One optimisation step on ``view`` (default: a sampled training view) through the
        stages of :data:`STEP_STAGES`; ``on_stage(name)`` is called after each (e.g. a
        benchmark's clock). Returns the step's loss, PSNR and loss terms."""
        state = StepState(self.sample_view() if view is None else view)
        self._step_started = time.perf_counter()
        for name in STEP_STAGES:
            getattr(self, f"stage_{name}")(state)
            if on_stage is not None:
                on_stage(name)
        return state.stats

    def stage_prepare(self, s: StepState) -> None:
        s.schedule_step = self.recon.schedule_step
        self.fit_sh_bands()
        s.factor = self.resolution_factor()
        s.camera = self.recon.camera(s.view).downscaled(s.factor)
        s.time = self.recon.time(s.view.frame)

    def stage_nodes(self, s: StepState) -> None:
        s.parts = self.recon.node_outputs(self.recon.drawn(s.time), s.camera, s.time, s.schedule_step)

    def stage_render(self, s: StepState) -> None:
        s.result = self.recon.render_outputs(s.parts, s.camera, s.time, step=s.schedule_step)

    def stage_lidar(self, s: StepState) -> None:
        if self.lidar is not None and self.step % self.config.method.lidar.every == 0:
            s.lidar_terms = self.lidar.loss_terms(self.config.method.lidar, self.step)

    def stage_loss(self, s: StepState) -> None:
        s.context = self.loss_context(s.view, s.result, s.factor)
        s.terms = {**self.loss_terms(s.context, s.result, s.camera, s.time), **s.lidar_terms}
        s.loss = sum(s.terms.values())
        if not torch.isfinite(s.loss):
            raise TrainingError(
                f"non-finite loss at step {self.step} (view camera={s.view.camera} frame={s.view.frame}; terms "
                + ", ".join(f"{k}={float(v):.4g}" for k, v in s.terms.items()) + "); no checkpoint was written"
            )
        with torch.no_grad():
            mse = float(masked_mean((s.result.rgb.detach().clamp(0, 1) - s.context.target) ** 2,
                                    dataclasses.replace(s.context, pixel_weights=None)))
        s.stats = {"loss": float(s.loss.detach()), "psnr": psnr_from_mse(mse),
                   **{k: float(v.detach()) for k, v in s.terms.items()}}

    def stage_backward(self, s: StepState) -> None:
        s.loss.backward()

    def stage_densify_stats(self, s: StepState) -> None:
        self.strategy.accumulate(self.model.gaussian_nodes(), s.result.slices, s.result.absgrad2d, s.result.radii,
                                 s.camera.width, s.camera.height)

    def stage_optimizer(self, s: StepState) -> None:
        self.optimizers.step(s.schedule_step)
        self.optimizers.zero_grad()
        self.recon.step += 1

    def stage_densify(self, s: StepState) -> None:
        seconds = self.train_seconds + (time.perf_counter() - self._step_started)
        # the clock's schedule step on a time budget (never back: a run resumed with a longer
        # budget waits for the clock); else one more (the step count, unless the run continues
        # a checkpoint whose schedule was ahead of its steps)
        if self.schedule.timed:
            now = max(s.schedule_step, self.schedule.position(self.step, seconds))
        else:
            now = s.schedule_step + 1
        self.strategy.step(self.model.gaussian_nodes(), self.optimizers, self.step, now, since=s.schedule_step)
        if self.densify_stop is None and s.schedule_step < self.strategy.refine_stop <= now:
            self.densify_stop = {"step": self.step, "schedule_step": now, "train_seconds": seconds,
                                 **self.prune_after_growth()}
        if self.schedule.timed or now != self.step:
            self.recon.schedule_step = now

    def train(self) -> dict:
        """Train until the budget is spent (``max_steps`` and/or ``max_seconds``: see
        :mod:`omnire.schedule`), checkpointing and evaluating on the way; returns the final
        evaluation, with the schedule as run under ``schedule``."""
        if self.run is None:
            raise ValueError("Trainer.train needs a run directory (persist=True)")
        tc = self.config.trainer
        self.write_run_info()
        file_log = logging.FileHandler(self.run.log_path)
        file_log.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
        omnire_log = logging.getLogger("omnire")
        omnire_log.addHandler(file_log)
        for record in self._early_records:
            file_log.handle(record)
        options = dict(option.split("=", 1) for option in tc.observer_options)
        self.observers = [self.plugins.train_observers.get(name).factory(self, options) for name in tc.observers]
        previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            return self._train_loop(tc)
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
            for observer in self.observers:
                observer.close()
            omnire_log.removeHandler(file_log)
            file_log.close()

    def _on_signal(self, signum: int, frame) -> None:
        self._stop_signal = signum

    def _train_loop(self, tc: TrainerConfig) -> dict:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        metrics_path = self.run.metrics_path
        schedule = self.schedule
        # the bar counts steps for a step budget, schedule steps (the clock's) for a time budget
        unit = "schedule steps, step {task.fields[step]}  " if schedule.timed else ""
        progress = Progress(
            TextColumn("[bold]train[/]"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
            TextColumn(unit + "loss {task.fields[loss]:.4f}  psnr {task.fields[psnr]:.2f}  {task.fields[its]:.2f} it/s  "
                       "{task.fields[ng]} G"),
            TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), disable=not tc.progress, transient=False,
        )

        def done() -> int:
            return self.recon.schedule_step if schedule.timed else self.step

        train_seconds = self.train_seconds  # time in training steps only (evaluation excluded), resumed runs included
        diverged: list[str] = []
        with progress, open(metrics_path, "a") as metrics:
            task = progress.add_task("train", total=schedule.steps if schedule.timed else schedule.max_steps,
                                     completed=done(), loss=0.0, psnr=0.0, its=0.0, step=self.step,
                                     ng=self.model.num_gaussians())
            window_n, window_seconds, window_psnr = 0, 0.0, []
            while not schedule.finished(self.step, train_seconds):
                if self._stop_signal is not None:
                    self._interrupt()
                t0 = time.perf_counter()
                stats = self.train_step()
                dt = time.perf_counter() - t0
                train_seconds += dt
                self.train_seconds = train_seconds
                last = schedule.finished(self.step, train_seconds)
                window_seconds += dt
                window_n += 1
                window_psnr.append(stats["psnr"])
                if self.step % tc.log_every == 0 or last:
                    its = window_n / max(window_seconds, 1e-9)
                    record = {"step": self.step, "wall": train_seconds, "its": its,
                              "num_gaussians": self.model.num_gaussians(), "schedule_step": self.recon.schedule_step,
                              **stats}
                    metrics.write(json.dumps(record) + "\n")
                    metrics.flush()
                    mean_psnr = sum(window_psnr) / len(window_psnr)
                    if self.step >= 4 * tc.log_every and mean_psnr < DIVERGENCE_PSNR and not diverged:
                        diverged.append(f"training PSNR fell to {mean_psnr:.1f} dB by step {self.step}")
                        progress.console.print(f"[yellow]warning:[/] {diverged[0]}: the run looks diverged "
                                               "(learning rates too high?)")
                        log.warning("%s: the run looks diverged", diverged[0])
                    window_seconds, window_n, window_psnr = 0.0, 0, []
                    progress.update(task, completed=done(), loss=stats["loss"], psnr=stats["psnr"], its=its,
                                    step=self.step, ng=record["num_gaussians"])
                if self.observers and (self.step % tc.observe_every == 0 or last):
                    for observer in self.observers:
                        observer.on_step(self.step, stats)
                if tc.eval_every and self.step % tc.eval_every == 0 and not last:
                    evaluation = self.evaluate()
                    metrics.write(json.dumps({"step": self.step, "wall": train_seconds, "eval": evaluation}) + "\n")
                if self.step % tc.checkpoint_every == 0 or last:
                    self.save_checkpoint()
            progress.update(task, completed=done(), step=self.step)
        if self._stop_signal is not None:
            self._interrupt()
        if not self.run.checkpoint_path(self.step).is_file():
            self.save_checkpoint()  # e.g. a branch of a finished run: its directory holds no checkpoint yet
        final = self.evaluate()
        final["train_seconds"] = train_seconds
        final["peak_rss_mb"] = peak_rss_mb()
        final["schedule"] = self.schedule_record()
        if diverged:
            final["warnings"] = diverged
        with open(metrics_path, "a") as metrics:
            metrics.write(json.dumps({"step": self.step, "wall": train_seconds, "eval": final, "final": True}) + "\n")
        self.write_run_info(final["schedule"])
        return final

    def _interrupt(self) -> None:
        name = signal.Signals(self._stop_signal).name
        path = self.save_checkpoint()
        raise TrainingInterrupted(f"{name}: stopped at step {self.step}; checkpoint {path} written "
                                  f"(continue with --trainer.resume {self.run.path})", self._stop_signal)

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def evaluate(self, write: bool = True) -> dict:
        from omnire.evaluation import evaluate

        if self.recon.renders_lidar and self._lidar_baselines is None:
            from omnire.lidar_evaluation import lidar_baselines

            self._lidar_baselines = lidar_baselines(self.scene) or {}  # once: training does not change them
        result = evaluate(self.recon, self.observations, self.train_views, self.test_views,
                          self.config.trainer.eval_train_views, self._lidar_baselines)
        if write and self.run is not None:
            atomic_write_text(self.run.path / "eval" / f"step-{self.step:06d}.json", json.dumps(result, indent=2))
        return result

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        for name, p in self.model.named_parameters():
            if not torch.isfinite(p).all():
                raise TrainingError(f"parameter {name} has non-finite values at step {self.step}; "
                                    "refusing to write a checkpoint")
        return {
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizers": self.optimizers.state_dict(),
            "strategy": self.strategy.state_dict(),
            "rng_torch": torch.get_rng_state(),
            "rng_sampler": self.sampler.get_state(),
            **({"rng_lidar": self.lidar.sampler.get_state()} if self.lidar is not None else {}),
            "train_seconds": self.train_seconds,
            "schedule_step": None if self.recon.schedule_step == self.step else self.recon.schedule_step,
            "densify_stop": self.densify_stop,
        }

    def save_checkpoint(self) -> Path:
        """Write ``checkpoints/step-N.pt`` atomically; a failed write (disk full, no
        permission) is a one-line error naming the path and leaves older checkpoints intact."""
        state = self.state_dict()
        path = self.run.checkpoint_path(self.step)
        buf = io.BytesIO()
        torch.save(state, buf)
        try:
            atomic_write_bytes(path, buf.getvalue())
        except OSError as exc:
            raise RunDirectoryError(f"{path}: cannot write checkpoint ({exc.strerror or exc}); "
                                    "the previous checkpoints are intact") from None
        return path

    def load_state(self, state: dict) -> None:
        """Continue from a checkpoint state (model, optimisers, densification, RNGs, the
        schedule's clock)."""
        self.recon.load_state(state)
        self.optimizers = Optimizers(self.model.optimizable(), self.schedule.steps)
        self.optimizers.load_state_dict(state["optimizers"])
        self.strategy.load_state_dict(state["strategy"])
        torch.set_rng_state(state["rng_torch"])
        self.sampler.set_state(state["rng_sampler"])
        if self.lidar is not None and "rng_lidar" in state:
            self.lidar.sampler.set_state(state["rng_lidar"])
        self.train_seconds = float(state.get("train_seconds", 0.0))
        self.densify_stop = state.get("densify_stop")
        if self.schedule.timed and state.get("schedule_step") is None:  # a step budget's, continued on the clock
            self.recon.schedule_step = self.schedule.position(self.step, self.train_seconds)
        self._sh_bands_degree = None


def _same_setting(mine, recorded, recorded_cwd: Path) -> bool:
    """Whether a setting of this process equals the recorded run's: equal values, or two
    strings naming the same path (relative ones against this process's working directory and
    the recorded run's ``recorded_cwd``: run.json's settings keep paths as given, its argv
    makes them absolute, so a run resumed from its recorded command line matches)."""
    if mine == recorded:
        return True
    if isinstance(mine, str) and isinstance(recorded, str) and mine and recorded:
        return (Path.cwd() / mine).resolve() == (recorded_cwd / recorded).resolve()
    return False


def _comparable(config) -> dict:
    """Flat {dotted field: value} of a config for comparing two runs' settings."""
    flat: dict = {}
    if config is None:
        return flat

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict) and "__type__" not in value:
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        elif isinstance(value, dict):
            for k, v in value.items():
                if k != "__type__":
                    walk(f"{prefix}.{k}" if prefix else k, v)
        else:
            flat[prefix] = value

    walk("", to_dict(config))
    return json.loads(json.dumps(flat))  # as stored in run.json (tuples become lists)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MB (Linux ru_maxrss is in KB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

