"""The core's commands: train, eval, render, plugins, bench raster / train / lidar / step.

User errors (:class:`~omnire.errors.UserError`) propagate to the CLI, which prints them as
one line; anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Literal, Optional

import tyro
from rich.table import Table

from omnire.errors import ConfigError
from omnire.runconfig import parse_train_args
from omnire.ui import output_console


def train_main(argv: list[str], plugins) -> int:
    from omnire.evaluation import format_camera_table, format_table
    from omnire.lidar_evaluation import format_lidar_table
    from omnire.trainer import Trainer

    config = parse_train_args(argv, plugins)
    console = output_console()
    trainer = Trainer(config, plugins, argv=argv)
    console.print(f"run directory: {trainer.run_dir}  rasterizer: {trainer.recon.rasterizer_name}  "
                  f"gaussians: {trainer.recon.num_gaussians()}  nodes: {list(trainer.recon.nodes)}")
    console.print(f"rasterizer paths: {trainer.recon.rasterizer_paths()}", highlight=False)
    result = trainer.train()
    console.print(format_table(result, f"{config.method_name} on {trainer.scene.name} at step {trainer.step}"))
    if len(trainer.scene.cameras) > 1 and (cameras := format_camera_table(result)) is not None:
        console.print(cameras)
    if (lidar := format_lidar_table(result)) is not None:
        console.print(lidar)
    for warning in result.get("warnings", []):
        console.print(f"[yellow]warning:[/] {warning}")
    return 0


@dataclasses.dataclass
class EvalArgs:
    """Evaluate a trained run on its training and held-out frames."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    checkpoint: Optional[Path] = None
    """Checkpoint file (default: the newest intact one in the run directory)."""
    train_views: int = 24
    """Training views evaluated for the reconstruction metrics (evenly spaced; 0 = all)."""


def eval_main(argv: list[str], plugins) -> int:
    import torch

    from omnire.evaluation import evaluate, format_camera_table, format_table
    from omnire.lidar_evaluation import format_lidar_table, lidar_baselines
    from omnire.observations import Observations
    from omnire.runtime import Reconstruction

    args = tyro.cli(EvalArgs, args=argv, prog="omnire eval")
    recon = Reconstruction.from_run(args.run_dir, plugins, args.checkpoint)
    scene = recon.scene
    baselines = lidar_baselines(scene) if recon.renders_lidar else None
    with torch.no_grad():
        result = evaluate(recon, Observations(scene, recon.device), scene.views(scene.train_frames),
                          scene.views(scene.test_frames), args.train_views, baselines)
    console = output_console()
    console.print(format_table(result, f"{recon.run_info.method} at step {recon.step}"))
    if len(scene.cameras) > 1 and (cameras := format_camera_table(result)) is not None:
        console.print(cameras)
    if (lidar := format_lidar_table(result)) is not None:
        console.print(lidar)
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
    video: bool = False
    """Also write an MP4 (H.264) per camera of the selected frames in time order."""
    fps: Optional[float] = None
    """With --video: interpolate the camera path to this frame rate over the selected frames' time span (the video
    then holds frames between the recorded ones; PNGs are written for the recorded frames only). Default: the
    recorded frames at the log's rate."""
    lidar: bool = False
    """Render LiDAR sweeps instead of images: a point cloud per frame, lidar/<frame>.ply and .npz
    (x, y, z, intensity, time, beam; omnire/lidarmodel.py), from the rays of the recorded sweep
    (its missing returns too, where the scene knows its beams) cast from the recorded sensor
    pose moved by --lidar-shift. Needs a run trained with --method.lidar.enabled."""
    lidar_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """With --lidar: move the sensor by this offset in its own frame (x forward, y left, z up), metres."""
    lidar_sectors: Optional[int] = None
    """With --lidar: time sectors per sweep (rolling shutter; default: the run's --method.lidar.sectors)."""


def render_lidar_frames(recon, frames: list[int], shift: tuple[float, float, float], sectors: int,
                        folder: Path) -> int:
    """Write the rendered sweep of each of ``frames`` as ``<folder>/<frame>.ply`` and ``.npz``
    (omnire/lidarpoints.py); returns the number of sweeps written (frames without LiDAR are
    skipped)."""
    import numpy as np

    from omnire.lidarpoints import sweep_points, write_point_cloud
    from omnire.lidarsweep import recorded_sweep, sensor_path, shifted_path

    path = shifted_path(sensor_path(recon.scene), np.asarray(shift, dtype=np.float64))
    count = 0
    for f in frames:
        sweep = recorded_sweep(recon.scene, int(f))
        if sweep is None:
            continue
        points = sweep_points(recon.render_sweep(sweep, path, sectors), sweep, path, sectors)
        write_point_cloud(folder / f"{recon.scene.source_frames[f]:03d}", points,
                          f"omnire render --lidar: frame {f}, sensor shift {list(shift)} m, step {recon.step}")
        count += 1
    return count


def render_main(argv: list[str], plugins) -> int:
    import contextlib

    import numpy as np
    import torch

    from omnire.data.scene import View
    from omnire.io.images import write_png
    from omnire.io.outputs import OutputError, check_location, staged_files
    from omnire.rundir import RunDirectory
    from omnire.runtime import Reconstruction

    args = tyro.cli(RenderArgs, args=argv, prog="omnire render")
    recon = Reconstruction.from_run(args.run_dir, plugins)
    scene = recon.scene
    cams = [scene.camera_index(n) for n in args.cameras] if args.cameras else list(range(len(scene.cameras)))
    if args.frames:
        bad = [f for f in args.frames if not 0 <= f < scene.num_frames]
        if bad:
            raise ConfigError(f"--frames {bad}: outside the loaded range 0..{scene.num_frames - 1}")
        frames = list(args.frames)
    else:
        frames = {"test": scene.test_frames, "train": scene.train_frames,
                  "all": np.arange(scene.num_frames)}[args.split].tolist()
    out_dir = args.output or Path(args.run_dir) / "renders"
    if Path(out_dir).resolve() == Path(args.run_dir).resolve():
        raise OutputError(f"--output {out_dir}: is the run directory; name a folder (default: <run dir>/renders)")
    check_location(out_dir, "--output", (RunDirectory(args.run_dir).data_path(),), replaces=False)
    if args.fps is not None and not (args.video and args.fps > 0):
        raise ConfigError(f"--fps {args.fps}: needs --video and a rate > 0")
    if args.lidar:
        if not recon.renders_lidar:
            raise ConfigError(f"--lidar: the run {args.run_dir} learned no LiDAR (train it with "
                              "--method.lidar.enabled on a scene with LiDAR)")
        sectors = args.lidar_sectors or recon.method.lidar.sectors
        if sectors < 1:
            raise ConfigError(f"--lidar-sectors {sectors}: must be >= 1")
        with torch.no_grad(), staged_files(out_dir) as staging:
            count = render_lidar_frames(recon, frames, args.lidar_shift, sectors, staging / "lidar")
        output_console().print(f"wrote {count} LiDAR sweeps to {Path(out_dir) / 'lidar'}")
        return 0
    count = 0
    # images and videos appear in out_dir when all are written (a failed write leaves none)
    with torch.no_grad(), staged_files(out_dir) as staging, contextlib.ExitStack() as stack:
        videos, path = {}, None
        if args.video:  # the camera path shared with omnire sim (omnire/camerapath.py)
            from omnire.camerapath import interpolated_path, log_seconds, recorded_fps
            from omnire.io.video import Mp4Writer

            frames = sorted(frames)
            if args.fps:
                sec = log_seconds(scene)
                path = interpolated_path(scene, args.fps, [scene.cameras[c].name for c in cams],
                                         float(sec[frames[0]]), float(sec[frames[-1]]))
            for c in cams:
                videos[c] = stack.enter_context(Mp4Writer(staging / f"{scene.cameras[c].name}.mp4",
                                                          args.fps or recorded_fps(scene)))
        for f in frames:
            for c in cams:
                view = View(c, int(f))
                result = recon.render(recon.camera(view).shifted(args.shift), recon.time(view.frame))
                name = f"{scene.source_frames[f]:03d}_{scene.cameras[c].name}"
                write_png(staging / f"{name}.png", result.rgb)
                if args.depth:
                    write_png(staging / f"{name}_depth.png", result.depth * 1000.0, bits=16)
                if videos and path is None:
                    videos[c].append(result.rgb)
                count += 1
        for i in range(len(path) if path is not None else 0):
            for k, c in enumerate(cams):
                videos[c].append(recon.render(path.camera(k, i, recon.device).shifted(args.shift),
                                              path.time(scene, i)).rgb)
    output_console().print(f"wrote {count} images{f' and {len(videos)} videos' if videos else ''} to {out_dir}")
    return 0


@dataclasses.dataclass
class PluginsArgs:
    """List every registry entry and the distribution providing it."""

    build: bool = False
    """Instead of the registries, compile every registered native extension now (those the
    cache already holds for these sources and this torch load at once) and list which are
    available; ``make install`` runs this, so that nothing compiles inside a first run."""


def build_native_extensions(plugins, console) -> None:
    """Load (compiling when needed) every registered native extension; print a table of the
    outcome: available with its load time, or unavailable with the reason (callers fall back
    to torch, so an unavailable one is reported, not fatal)."""
    table = Table(title="native extensions")
    for col in ("name", "distribution", "status", "seconds"):
        table.add_column(col)
    registry = plugins.native_extensions
    for name, spec in registry.items():
        start = time.perf_counter()
        module, reason = spec.load()
        status = "available" if module is not None else f"[red]unavailable:[/] {reason}"
        table.add_row(name, registry.provenance(name).distribution, status, f"{time.perf_counter() - start:.1f}")
    console.print(table)


def plugins_main(argv: list[str], plugins) -> int:
    from omnire.rasterization import summarize_paths

    args = tyro.cli(PluginsArgs, args=argv, prog="omnire plugins")
    console = output_console()
    if args.build:
        build_native_extensions(plugins, console)
        return 0
    for attr, registry in plugins.registries().items():
        table = Table(title=f"{attr.replace('_', ' ')}")
        rasterizers = attr == "rasterizers"  # and which path each optional capability takes
        for col in ("name", "description", "distribution", "version") + (("paths",) if rasterizers else ()):
            table.add_column(col)
        for name, spec in registry.items():
            prov = registry.provenance(name)
            table.add_row(name, spec.description, prov.distribution, prov.version,
                          *((summarize_paths(spec.capabilities),) if rasterizers else ()))
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


def bench_lidar_main(argv: list[str], plugins) -> int:
    from omnire.bench import lidar

    return int(lidar.main(argv, plugins) or 0)


def bench_step_main(argv: list[str], plugins) -> int:
    from omnire.bench import step

    return int(step.main(argv, plugins) or 0)

