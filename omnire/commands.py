"""The core's commands: train, eval, render, plugins, bench."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import tyro
from rich.console import Console
from rich.table import Table

from omnire.trainer import TrainConfig, Trainer, TrainerConfig, TrainingError, find_checkpoint

# Errors that mean "bad input": print the message (it names the file/field) and exit 2.
from omnire.data.images import ImageReadError
from omnire.data.scene import SceneDataError
from omnire.model import ModelBuildError
from omnire.registry import RegistryError

USER_ERRORS = (SceneDataError, ImageReadError, FileNotFoundError, NotADirectoryError, RegistryError,
               ModelBuildError, TrainingError, ValueError)


def _user_error(exc: Exception) -> int:
    Console(stderr=True).print(f"[red]error:[/] {exc}", highlight=False)
    return 2


def train_cli_type(plugins):
    """Union over methods of dataclasses (dataparser subcommand, method, trainer), built
    from the registries at call time."""
    dp_types = []
    for spec in plugins.dataparsers:
        default = spec.config_factory()
        dp_types.append(Annotated[type(default), tyro.conf.subcommand(spec.name, default=default,
                                                                       description=spec.description)])
    if not dp_types:
        raise RegistryError("no dataparser is installed (e.g. pip install -e dataparsers/pandaset)")
    dp_union = _subcommand_union(dp_types)
    method_types = []
    for spec in plugins.methods:
        default = spec.config_factory()
        cls = dataclasses.make_dataclass(
            f"Train_{spec.name}",
            [
                ("dataparser", tyro.conf.OmitArgPrefixes[dp_union]),
                ("method", type(default), dataclasses.field(default_factory=spec.config_factory)),
                ("trainer", TrainerConfig, dataclasses.field(default_factory=TrainerConfig)),
            ],
        )
        cls._method_name = spec.name
        method_types.append(Annotated[cls, tyro.conf.subcommand(spec.name, description=spec.description)])
    if not method_types:
        raise RegistryError("no method is registered")
    return _subcommand_union(method_types)


def _subcommand_union(types: list):
    # A Union needs two members; a suppressed None keeps a single entry a subcommand.
    return Union[tuple(types) + (Annotated[None, tyro.conf.Suppress],)]


def parse_train_args(argv: list[str], plugins) -> TrainConfig:
    parsed = tyro.cli(
        train_cli_type(plugins), args=argv, prog="omnire train",
        config=(tyro.conf.OmitSubcommandPrefixes, tyro.conf.CascadeSubcommandArgs, tyro.conf.SuppressFixed),
    )
    dp_name = next(s.name for s in plugins.dataparsers if type(s.config_factory()) is type(parsed.dataparser))
    return TrainConfig(type(parsed)._method_name, dp_name, parsed.method, parsed.dataparser, parsed.trainer)


def train_main(argv: list[str], plugins) -> int:
    config = parse_train_args(argv, plugins)
    console = Console()
    try:
        trainer = Trainer(config, plugins, argv=argv)
        console.print(f"run directory: {trainer.run_dir}  rasterizer: {trainer.rasterizer.name}  "
                      f"gaussians: {trainer.model.num_gaussians()}  nodes: {list(trainer.model.nodes)}")
        result = trainer.train()
    except USER_ERRORS as exc:
        return _user_error(exc)
    from omnire.evaluation import format_table

    console.print(format_table(result, f"{config.method_name} on {trainer.scene.name} at step {trainer.step}"))
    return 0


def trainer_from_run(run_dir: Path, plugins, checkpoint: Optional[Path] = None) -> Trainer:
    """Rebuild the trainer of a run directory from its recorded arguments and load a checkpoint."""
    run_dir = Path(run_dir)
    info_path = run_dir / "run.json"
    if not info_path.is_file():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no run.json)")
    info = json.loads(info_path.read_text())
    config = parse_train_args(info["argv"], plugins)
    config.trainer.resume = None
    trainer = Trainer(config, plugins, argv=info["argv"], run_dir=run_dir)
    trainer.load_checkpoint(find_checkpoint(checkpoint or run_dir))
    return trainer


@dataclasses.dataclass
class EvalArgs:
    """Evaluate a trained run on its training and held-out frames."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    checkpoint: Optional[Path] = None
    """Checkpoint file (default: the latest in the run directory)."""


def eval_main(argv: list[str], plugins) -> int:
    args = tyro.cli(EvalArgs, args=argv, prog="omnire eval")
    try:
        trainer = trainer_from_run(args.run_dir, plugins, args.checkpoint)
        result = trainer.evaluate()
    except USER_ERRORS as exc:
        return _user_error(exc)
    from omnire.evaluation import format_table

    Console().print(format_table(result, f"{trainer.config.method_name} at step {trainer.step}"))
    return 0


@dataclasses.dataclass
class RenderArgs:
    """Render frames of a trained run to image files (PNG)."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    split: Literal["test", "train", "all"] = "test"
    """Which frames, when --frames is not given."""
    frames: tuple[int, ...] = ()
    """Frame indices (0-based within the loaded range) to render."""
    cameras: tuple[str, ...] = ()
    """Camera names (default: all)."""
    shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Move the camera by this offset in its own frame (x right, y down, z forward), metres."""
    output: Optional[Path] = None
    """Output directory (default: <run dir>/renders)."""
    depth: bool = False
    """Also write depth images (16-bit PNG, millimetres)."""


def render_main(argv: list[str], plugins) -> int:
    import numpy as np
    import torch

    from omnire.data.scene import View
    from omnire.io.images import write_png

    args = tyro.cli(RenderArgs, args=argv, prog="omnire render")
    try:
        trainer = trainer_from_run(args.run_dir, plugins)
        scene = trainer.scene
        cams = [scene.camera_index(n) for n in args.cameras] if args.cameras else list(range(len(scene.cameras)))
        if args.frames:
            bad = [f for f in args.frames if not 0 <= f < scene.num_frames]
            if bad:
                raise ValueError(f"--frames {bad}: outside the loaded range 0..{scene.num_frames - 1}")
            frames = list(args.frames)
        else:
            frames = {"test": scene.test_frames, "train": scene.train_frames,
                      "all": np.arange(scene.num_frames)}[args.split].tolist()
    except USER_ERRORS as exc:
        return _user_error(exc)
    out_dir = args.output or Path(args.run_dir) / "renders"
    shift = torch.tensor(args.shift, dtype=torch.float32)
    count = 0
    with torch.no_grad():
        for f in frames:
            for c in cams:
                view = View(c, int(f))
                K, c2w, W, H = trainer.model.camera(view)
                c2w = c2w.clone()
                c2w[:3, 3] += c2w[:3, :3] @ shift
                result = trainer.model.render(view, trainer.sh_degree(), camera_override=(K, c2w, W, H))
                name = f"{scene.source_frames[f]:03d}_{scene.cameras[c].name}"
                write_png(out_dir / f"{name}.png", result.rgb)
                if args.depth:
                    write_png(out_dir / f"{name}_depth.png", result.depth * 1000.0, bits=16)
                count += 1
    Console().print(f"wrote {count} images to {out_dir}")
    return 0


def plugins_main(argv: list[str], plugins) -> int:
    console = Console()
    for attr, registry in plugins.registries().items():
        table = Table(title=f"{attr.replace('_', ' ')}")
        for col in ("name", "description", "distribution", "version"):
            table.add_column(col)
        for name, spec in registry.items():
            prov = registry.provenance(name)
            table.add_row(name, spec.description, prov.distribution, prov.version)
        console.print(table)
    if plugins.failures:
        table = Table(title="plugins that failed to load", style="red")
        for col in ("plugin", "distribution", "version", "stage", "error"):
            table.add_column(col)
        for f in plugins.failures:
            table.add_row(f.plugin, f.provenance.distribution, f.provenance.version, f.stage, f.error)
        console.print(table)
    return 0


def bench_raster_main(argv: list[str], plugins) -> int:
    from omnire.bench import raster

    return int(raster.main(argv, plugins) or 0)


def bench_train_main(argv: list[str], plugins) -> int:
    from omnire.bench import train

    return int(train.main(argv, plugins) or 0)


def bench_skip_main(argv: list[str], plugins) -> int:
    from omnire.bench import skip

    return int(skip.main(argv, plugins) or 0)
