"""``omnire bench step``: where the time of one training step goes.

Builds the trainer of ``omnire train <method> <dataparser>`` in memory (nothing written),
optionally loads a trained run's checkpoint (``--checkpoint``: its Gaussians, optimiser state
and step; the run must have the same method settings and data selection), optionally
resizes the background node to ``--gaussians`` rows (seeded resampling with replacement of
its rows, optimiser state carried along) and puts the step counter at ``--at-step`` (SH
bands and schedules as at that step, and the SH coefficients stored as training stores them
then: up to that step's degree, see omnire/shbands.py). The recorded data of every view it
will use is decoded first (a training run has its images cached after the first pass over
the views). Then it runs ``--steps`` real training steps (:meth:`Trainer.train_step`: the
step's resolution, SH fitting, densification when the schedule says so, the step counter
advancing) and times each of its named stages (:data:`omnire.trainer.STEP_STAGES`:
``prepare``, ``nodes``, ``render``, ``loss``, ``backward``, ``densify_stats``,
``optimizer``, ``densify``) and ``total``, their sum (wall clock; ``total_cpu``: the
process's CPU time, less sensitive to other processes on a shared machine). With ``--paths
fused unfused`` (default: both when the rasterizer declares the ``fused_training``
capability) the render paths alternate step by step on the same views in one process, so a
shared machine's load affects them alike. Views are sampled with a seeded generator of their
own. Medians and quartiles in ms; JSON to ``--output`` (atomic) and a table on the console.
"""
from __future__ import annotations

import dataclasses
import json
import statistics
import time
from pathlib import Path
from typing import Optional

import tyro

from omnire.errors import ConfigError
from omnire.bench.machine import machine_info, machine_line
from omnire.io.atomic import atomic_write_text
from omnire.shbands import sh_columns
from omnire.trainer import STEP_STAGES
from omnire.ui import output_console

STAGES = STEP_STAGES


@dataclasses.dataclass
class StepBenchArgs:
    """Per-stage time of a training step."""

    dataparser: str
    """Dataparser name (``omnire plugins`` lists them), e.g. pandaset."""
    data: Path
    """Scene directory, e.g. data/demo/pandaset_002."""
    method: str = "omnire"
    """Method to train."""
    method_args: str = ""
    """Extra method / trainer flags as one string, e.g. --method-args="--method.nodes.smpl.pose-source neutral"."""
    dataparser_args: str = "--scale 1.0"
    """Extra dataparser flags as one string."""
    checkpoint: Optional[Path] = None
    """A run directory (its newest checkpoint) or checkpoint file of this method on this data:
    benchmark its trained Gaussians instead of the initialised ones."""
    gaussians: int = 0
    """Background Gaussians to benchmark with (0: as initialised, or as in --checkpoint)."""
    at_step: Optional[int] = None
    """Training step the benchmark runs at (SH bands, learning-rate schedules; default: the
    checkpoint's step, or 0; a checkpoint of a time budget: the schedule step it stopped at,
    omnire/schedule.py)."""
    warmup: int = 3
    """Untimed steps per path."""
    steps: int = 20
    """Timed steps per path."""
    threads: int = 1
    """torch / rasterizer threads."""
    paths: tuple[str, ...] = ()
    """Render paths to compare: fused (the rasterizer's fused training path) and/or unfused
    (assemble + composite); default: both when the rasterizer has a fused path."""
    seed: int = 0
    """Seed of the resampling and of the view order."""
    output: Path = Path("outputs/bench/step.json")
    """Where the JSON results go."""


def build_trainer(args: StepBenchArgs, plugins):
    import shlex

    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    argv = [args.method, args.dataparser, "--data", str(args.data), *shlex.split(args.dataparser_args),
            *shlex.split(args.method_args), "--trainer.threads", str(args.threads), "--trainer.no-progress"]
    config = parse_train_args(argv, plugins)
    return Trainer(config, plugins, argv=argv, persist=False)


def load_run_state(trainer, path: Path) -> None:
    """Put ``trainer`` in the state of the checkpoint at ``path`` (a run directory or a
    checkpoint file), refusing a run of another method, method settings or data selection."""
    from omnire.rundir import find_checkpoint

    source, _ckpt, state = find_checkpoint(path)
    trainer.check_run_matches(source.read_info())
    trainer.load_state(state)


def resize_background(trainer, n: int, seed: int) -> None:
    """Resample the largest Gaussian node ("background" when present) to ``n`` rows."""
    import torch

    nodes = trainer.model.gaussian_nodes()
    if not nodes:
        raise ConfigError("--gaussians: the method has no Gaussian node")
    name = "background" if "background" in nodes else max(nodes, key=lambda k: nodes[k].num_gaussians)
    node = nodes[name]
    if node.num_gaussians == 0:
        raise ConfigError(f"--gaussians: node {name!r} has no Gaussians to resample")
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(node.num_gaussians, (n,), generator=g)
    idx = idx.to(node.gaussian_params["means"].device)
    trainer.optimizers.replace_gaussian_rows(name, node, lambda k, t: t[idx].clone(), lambda k, s: s[idx].clone())


def time_step(trainer, view, fused: bool) -> tuple[dict[str, float], dict[str, float]]:
    """One training step on ``view`` with the chosen render path: seconds per stage, wall
    clock and process CPU time."""
    trainer.recon.use_fused_training = fused
    marks = [(time.perf_counter(), time.process_time())]
    trainer.train_step(view, on_stage=lambda _name: marks.append((time.perf_counter(), time.process_time())))
    wall = {k: b[0] - a[0] for k, a, b in zip(STAGES, marks, marks[1:])}
    cpu = {k: b[1] - a[1] for k, a, b in zip(STAGES, marks, marks[1:])}
    return wall, cpu


def summarize(samples: list[float]) -> dict[str, float]:
    s = sorted(1000.0 * x for x in samples)
    q = statistics.quantiles(s, n=4) if len(s) > 1 else [s[0]] * 3
    return {"median_ms": round(statistics.median(s), 2), "q25_ms": round(q[0], 2), "q75_ms": round(q[2], 2)}


def run(args: StepBenchArgs, plugins) -> dict:
    import torch

    torch.set_num_threads(max(1, args.threads))
    if args.steps < 1 or args.warmup < 0:
        raise ConfigError(f"--steps must be >= 1 and --warmup >= 0, got {args.steps} / {args.warmup}")
    trainer = build_trainer(args, plugins)
    model = trainer.model
    has_fused = "fused_training" in model.capabilities
    paths = args.paths or (("fused", "unfused") if has_fused else ("unfused",))
    bad = [p for p in paths if p not in ("fused", "unfused")]
    if bad:
        raise ConfigError(f"--paths {bad}: expected fused and/or unfused")
    if "fused" in paths and not has_fused:
        raise ConfigError(f"--paths fused: rasterizer {trainer.recon.rasterizer_name!r} does not declare the "
                          "fused_training capability (rasterize_gaussians_train); use --method.rasterizer cpu")
    if args.checkpoint is not None:
        load_run_state(trainer, args.checkpoint)
    if args.gaussians:
        resize_background(trainer, args.gaussians, args.seed)
    if args.at_step is not None:
        trainer.recon.step, trainer.recon.schedule_step = args.at_step, None  # its schedules as at that step
    at_step = trainer.recon.schedule_step  # 0, the checkpoint's (a time budget's: where its schedule stopped)
    # SH bands as training at ``at_step`` stores them (omnire/shbands.py); a checkpoint of a
    # later degree loses its higher bands here, which that step would not have yet
    trainer.fit_sh_bands(discard_unused=True)
    g = torch.Generator().manual_seed(args.seed)
    views = [trainer.train_views[int(torch.randint(len(trainer.train_views), (1,), generator=g))]
             for _ in range(args.warmup + args.steps)]
    trainer.observations.preload(views, sky=trainer.use_sky_masks)
    # what the benchmark starts from (the steps' densification may change it)
    start = {"sh_degree": trainer.recon.sh_degree(at_step), "gaussians": model.num_gaussians(),
             "gaussians_by_node": {n: m.num_gaussians for n, m in model.gaussian_nodes().items()},
             "sh_columns_by_node": sh_columns(model.gaussian_nodes())}
    samples = {p: {s: [] for s in (*STAGES, "total")} for p in paths}
    cpu_total = {p: [] for p in paths}
    for i, view in enumerate(views):
        order = paths if i % 2 == 0 else tuple(reversed(paths))
        for p in order:
            wall, cpu = time_step(trainer, view, p == "fused")
            if i >= args.warmup:
                for k, v in wall.items():
                    samples[p][k].append(v)
                samples[p]["total"].append(sum(wall.values()))
                cpu_total[p].append(sum(cpu.values()))
    trainer.recon.use_fused_training = True
    return {
        "machine": machine_info(args.threads),
        "method": args.method, "dataparser": args.dataparser, "data": str(args.data),
        "rasterizer": trainer.recon.rasterizer_name, "threads": args.threads, "at_step": at_step,
        "steps_taken_to": trainer.step, "gaussians_after": model.num_gaussians(),
        "checkpoint": None if args.checkpoint is None else str(args.checkpoint), **start,
        "warmup": args.warmup, "steps": args.steps,
        "paths": {p: {**{k: summarize(v) for k, v in samples[p].items()}, "total_cpu": summarize(cpu_total[p])}
                  for p in paths},
    }


def print_table(result: dict) -> None:
    from rich.table import Table

    paths = list(result["paths"])
    table = Table(title=f"{result['method']} step at {result['gaussians']} Gaussians, SH degree {result['sh_degree']}, "
                        f"{result['threads']} thread(s): median ms (q25-q75)")
    table.add_column("stage")
    for p in paths:
        table.add_column(p, justify="right")
    for stage in (*STAGES, "total", "total_cpu"):
        table.add_row(stage, *(f"{result['paths'][p][stage]['median_ms']:.1f} "
                               f"({result['paths'][p][stage]['q25_ms']:.1f}-{result['paths'][p][stage]['q75_ms']:.1f})"
                               for p in paths))
    output_console().print(table)
    if "machine" in result:
        output_console().print(f"on {machine_line(result['machine'])}")


def main(argv: list[str], plugins) -> int:
    args = tyro.cli(StepBenchArgs, args=argv, prog="omnire bench step")
    result = run(args, plugins)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.output, json.dumps(result, indent=2) + "\n")
    print_table(result)
    output_console().print(f"wrote {args.output}")
    return 0
