"""Training loop, evaluation, checkpoints.

A run directory holds ``run.json`` (the exact CLI arguments, so ``omnire eval`` and
``omnire render`` rebuild the same configuration without unpickling anything),
``metrics.jsonl`` (one JSON object per logged step / evaluation), ``checkpoints/`` and
``eval/``. Checkpoints hold the model, optimiser moments, densification state and every
RNG state, so a resumed run continues exactly like an uninterrupted one.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any, Optional

import torch

from omnire.data.images import ImageCache
from omnire.data.scene import SceneData, View
from omnire.io.atomic import atomic_write_bytes, atomic_write_text
from omnire.lidar import LidarDepthTargets
from omnire.losses import LossContext
from omnire.masks import DynamicMasks, SkyMasks
from omnire.method import MethodConfig
from omnire.model import SceneModel
from omnire.optim import Optimizers
from omnire.rasterization import select_rasterizer
from omnire.strategy import AbsGradStrategy


class TrainingError(RuntimeError):
    """Training cannot continue (non-finite loss or parameters); nothing bad was saved."""


@dataclasses.dataclass
class TrainerConfig:
    """Loop, logging, evaluation and checkpoint settings."""

    max_steps: int = 3000
    """Training iterations (one image per step); learning-rate schedules span them."""
    max_seconds: float = 0.0
    """Stop earlier once training (not evaluation) has taken this many seconds (0: no limit)."""
    eval_every: int = 0
    """Evaluate on the held-out frames every N steps (0: only at the end)."""
    log_every: int = 25
    """Write training metrics every N steps."""
    checkpoint_every: int = 1000
    """Save a checkpoint every N steps (and always at the end)."""
    output_dir: Path = Path("outputs")
    """Where run directories are created."""
    run_name: Optional[str] = None
    """Run directory name (default: <scene>-<method>-<time>)."""
    seed: int = 0
    """Seed for initialisation, view sampling and densification."""
    threads: int = 0
    """torch CPU threads (0: torch's default)."""
    device: str = "cpu"
    """Torch device (cpu or cuda)."""
    resume: Optional[Path] = None
    """Resume from a checkpoint file or the latest checkpoint of a run directory."""
    eval_train_views: int = 24
    """Training views evaluated for the reconstruction metrics (evenly spaced; 0 = all)."""
    progress: bool = True
    """Show the rich progress bar."""


@dataclasses.dataclass
class TrainConfig:
    """What ``omnire train <method> <dataparser>`` builds."""

    method_name: str
    dataparser_name: str
    method: MethodConfig
    dataparser: Any
    trainer: TrainerConfig


def psnr_from_mse(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


class Trainer:
    def __init__(self, config: TrainConfig, plugins, argv: Optional[list[str]] = None,
                 run_dir: Optional[Path] = None, scene: Optional[SceneData] = None) -> None:
        self.config = config
        self.plugins = plugins
        tc = config.trainer
        if tc.threads > 0:
            torch.set_num_threads(tc.threads)
        self.device = torch.device(tc.device)
        torch.manual_seed(tc.seed)
        self.scene = scene if scene is not None else config.dataparser.setup().parse().validate()
        self.images = ImageCache()
        self.rasterizer = select_rasterizer(plugins.rasterizers, config.method.rasterizer, self.device)
        self.losses = {}
        for name, weight in config.method.loss_weights.items():
            if weight != 0:
                self.losses[name] = (plugins.losses.get(name).fn, weight)
        self.model = SceneModel(config.method, self.scene, plugins.node_types, self.images, self.rasterizer,
                                self.device, seed=tc.seed)
        self.optimizers = Optimizers(dict(self.model.nodes), tc.max_steps)
        self.strategy = AbsGradStrategy(config.method.densify, self.model.scene_radius, tc.max_steps)
        self.lidar = LidarDepthTargets(self.scene, self.device)
        self.dynamic_masks = DynamicMasks(self.scene, self.images, self.device)
        has_env = any(m.is_environment for m in self.model.nodes.values())
        # sky masks only feed the opacity loss, which only means something with a sky node
        self.sky_masks = SkyMasks(self.scene, self.images, self.device) if has_env and "opacity" in self.losses else None
        self.sampler = torch.Generator().manual_seed(tc.seed + 1)
        self.train_views = self.scene.views(self.scene.train_frames)
        self.test_views = self.scene.views(self.scene.test_frames)
        self.step = 0
        self.run_dir = run_dir or self._new_run_dir()
        self.argv = argv
        if tc.resume is not None:
            self.load_checkpoint(find_checkpoint(tc.resume))

    # ------------------------------------------------------------------ set-up helpers
    def _new_run_dir(self) -> Path:
        tc = self.config.trainer
        name = tc.run_name or f"{self.scene.name}-{self.config.method_name}-{time.strftime('%Y%m%d-%H%M%S')}"
        return Path(tc.output_dir) / name

    def write_run_info(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        info = {
            "argv": self.argv,
            "method": self.config.method_name,
            "dataparser": self.config.dataparser_name,
            "rasterizer": self.rasterizer.name,
            "scene": self.scene.name,
            "attribution": self.scene.attribution,
            "node_assignment": self.model.assignment,
            "plugins": [[n, p.distribution, p.version] for n, p in self.plugins.loaded],
        }
        atomic_write_text(self.run_dir / "run.json", json.dumps(info, indent=2))

    def sh_degree(self) -> int:
        return min(3, self.step // max(1, self.config.method.sh_degree_interval))

    def target(self, view: View) -> torch.Tensor:
        return self.images.camera_image(self.scene.cameras[view.camera], view.frame).to(self.device)

    # ------------------------------------------------------------------ training
    def loss_context(self, view: View, result) -> LossContext:
        lidar = self.lidar.get(view) if "depth" in self.losses else None
        weight = self.config.method.dynamic_pixel_weight
        pixel_weights = None
        if weight != 1.0 and self.scene.tracks:
            pixel_weights = 1.0 + (weight - 1.0) * self.dynamic_masks.get(view, "all")
        return LossContext(
            rgb=result.rgb, depth=result.depth, alpha=result.alpha, target=self.target(view),
            pixel_weights=pixel_weights,
            lidar_pixels=None if lidar is None else lidar[0], lidar_depth=None if lidar is None else lidar[1],
            sky_mask=self.sky_masks.get(view) if self.sky_masks is not None else None,
            step=self.step,
        )

    def train_step(self) -> dict[str, float]:
        i = int(torch.randint(len(self.train_views), (1,), generator=self.sampler))
        view = self.train_views[i]
        result = self.model.render(view, self.sh_degree(), step=self.step)
        ctx = self.loss_context(view, result)
        terms: dict[str, torch.Tensor] = {}
        for name, (fn, weight) in self.losses.items():
            value = fn(ctx)
            if value is not None:
                terms[name] = weight * value
        reg_w = self.config.method.regularization_weights
        for node in self.model.nodes.values():
            for name, value in node.regularization(view.frame, float(self.scene.frame_timestamps[view.frame])).items():
                if reg_w.get(name, 0.0) != 0.0:
                    terms[name] = reg_w[name] * value
        loss = sum(terms.values())
        if not torch.isfinite(loss):
            raise TrainingError(
                f"non-finite loss at step {self.step} (view camera={view.camera} frame={view.frame}; terms "
                + ", ".join(f"{k}={float(v):.4g}" for k, v in terms.items()) + "); no checkpoint was written"
            )
        loss.backward()
        cam = self.scene.cameras[view.camera]
        self.strategy.accumulate(self.model.gaussian_nodes(), result.slices, result.absgrad2d, result.radii,
                                 cam.width, cam.height)
        self.optimizers.step(self.step)
        self.optimizers.zero_grad()
        self.step += 1
        self.strategy.step(self.model.gaussian_nodes(), self.optimizers, self.step)
        with torch.no_grad():
            mse = float(((result.rgb.detach().clamp(0, 1) - ctx.target) ** 2).mean())
        return {"loss": float(loss.detach()), "psnr": psnr_from_mse(mse), **{k: float(v.detach()) for k, v in terms.items()}}

    def train(self) -> dict:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        tc = self.config.trainer
        self.write_run_info()
        metrics_path = self.run_dir / "metrics.jsonl"
        progress = Progress(
            TextColumn("[bold]train[/]"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
            TextColumn("loss {task.fields[loss]:.4f}  psnr {task.fields[psnr]:.2f}  {task.fields[its]:.2f} it/s  "
                       "{task.fields[ng]} G"),
            TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), disable=not tc.progress, transient=False,
        )
        train_seconds = 0.0  # time in training steps only (evaluation excluded)
        last_eval = None
        with progress, open(metrics_path, "a") as log:
            task = progress.add_task("train", total=tc.max_steps, completed=self.step, loss=0.0, psnr=0.0, its=0.0,
                                     ng=self.model.num_gaussians())
            window_n = 0
            window_seconds = 0.0
            while self.step < tc.max_steps and not (tc.max_seconds and train_seconds >= tc.max_seconds):
                t0 = time.perf_counter()
                stats = self.train_step()
                dt = time.perf_counter() - t0
                train_seconds += dt
                window_seconds += dt
                window_n += 1
                if self.step % tc.log_every == 0 or self.step == tc.max_steps:
                    its = window_n / max(window_seconds, 1e-9)
                    window_seconds, window_n = 0.0, 0
                    record = {"step": self.step, "wall": train_seconds, "its": its,
                              "num_gaussians": self.model.num_gaussians(), **stats}
                    log.write(json.dumps(record) + "\n")
                    log.flush()
                    progress.update(task, completed=self.step, loss=stats["loss"], psnr=stats["psnr"], its=its,
                                    ng=record["num_gaussians"])
                if tc.eval_every and self.step % tc.eval_every == 0 and self.step < tc.max_steps:
                    last_eval = self.evaluate()
                    log.write(json.dumps({"step": self.step, "wall": train_seconds, "eval": last_eval}) + "\n")
                if self.step % tc.checkpoint_every == 0 or self.step == tc.max_steps:
                    self.save_checkpoint()
            progress.update(task, completed=self.step)
        if self.step % tc.checkpoint_every != 0 and self.step != tc.max_steps:
            self.save_checkpoint()  # stopped by the time budget
        last_eval = self.evaluate()
        last_eval["train_seconds"] = train_seconds
        last_eval["peak_rss_mb"] = peak_rss_mb()
        with open(metrics_path, "a") as log:
            log.write(json.dumps({"step": self.step, "wall": train_seconds, "eval": last_eval, "final": True}) + "\n")
        return last_eval

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def evaluate(self, write: bool = True) -> dict:
        from omnire.evaluation import evaluate_model

        result = evaluate_model(self)
        if write:
            atomic_write_text(self.run_dir / "eval" / f"step-{self.step:06d}.json", json.dumps(result, indent=2))
        return result

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self) -> Path:
        for name, p in self.model.named_parameters():
            if not torch.isfinite(p).all():
                raise TrainingError(f"parameter {name} has non-finite values at step {self.step}; "
                                    "refusing to write a checkpoint")
        state = {
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizers": self.optimizers.state_dict(),
            "strategy": self.strategy.state_dict(),
            "rng_torch": torch.get_rng_state(),
            "rng_sampler": self.sampler.get_state(),
        }
        path = self.run_dir / "checkpoints" / f"step-{self.step:06d}.pt"
        import io

        buf = io.BytesIO()
        torch.save(state, buf)
        atomic_write_bytes(path, buf.getvalue())
        return path

    def load_checkpoint(self, path: Path) -> None:
        state = torch.load(path, map_location=self.device, weights_only=True)
        for name, node in self.model.nodes.items():
            node.prepare_load(state["model"], prefix=f"nodes.{name}.")
        self.model.load_state_dict(state["model"])
        self.optimizers = Optimizers(dict(self.model.nodes), self.config.trainer.max_steps)
        self.optimizers.load_state_dict(state["optimizers"])
        self.strategy.load_state_dict(state["strategy"])
        torch.set_rng_state(state["rng_torch"])
        self.sampler.set_state(state["rng_sampler"])
        self.step = int(state["step"])


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MB (Linux ru_maxrss is in KB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def find_checkpoint(path: Path) -> Path:
    """A checkpoint file, or the latest ``checkpoints/step-*.pt`` of a run directory."""
    path = Path(path)
    if path.is_file():
        return path
    ckpts = sorted((path / "checkpoints").glob("step-*.pt"))
    if not ckpts:
        raise FileNotFoundError(f"{path}: no checkpoint file and no checkpoints/step-*.pt inside")
    return ckpts[-1]
