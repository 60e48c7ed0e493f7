"""``omnire compact``: a smaller copy of a trained run (docs/compact.md).

The new run is made by the real :class:`~omnire.api.Trainer`, branched from the source
checkpoint into a hidden sibling folder (``.<name>.partial``): evaluated, pruned node by node
(:func:`omnire.api.prune_nodes`), optionally fine-tuned, checkpointed, evaluated again, and only
then renamed to ``--output``; a failure or Ctrl-C leaves no half-written run behind.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from pathlib import Path
from typing import Optional

import tyro

from omnire.api import ConfigError, Reconstruction, RunDirectory, Trainer, UserError, atomic_write_text

DEFAULT_FINETUNE_STEPS = 300
"""Fine-tuning steps after pruning by default, as measured on the trained demo run
(docs/compact.md, "Measurements"): keeping half of its 412k Gaussians costs 0.09 dB held-out
PSNR and 0.5 dB in the human regions without fine-tuning; 300 steps (a tenth of its 3200)
recover both and more, at 40% as at 50%."""

SET_BY_COMPACT = ("--trainer.resume", "--trainer.output-dir", "--trainer.run-name", "--trainer.max-steps",
                  "--trainer.max-seconds")
"""Flags of the source run's recorded command line that the compacted run records anew."""


@dataclasses.dataclass
class CompactArgs:
    """Write a smaller copy of a trained run: in every node (background, each actor instance,
    bodies) keep the given fraction of the Gaussians that contribute most to the training
    views (summed blending weight), optionally fine-tune, and report size, Gaussian count,
    render speed and held-out PSNR before and after (also in <output>/compact.json)."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    output: Path
    """The new run directory (must not exist)."""
    keep_fraction: float = 0.5
    """Fraction of each node's Gaussians kept (of each actor instance's for actor nodes), 0 < f <= 1."""
    finetune_steps: int = DEFAULT_FINETUNE_STEPS
    """Training steps after pruning, on the training views with the run's own trainer, losses and
    learning rates (the schedule extended by these steps; 0: none)."""
    checkpoint: Optional[Path] = None
    """Checkpoint of the source run to compact (default: its newest intact one)."""
    eval_train_views: int = 8
    """Training views evaluated for the reconstruction metrics (evenly spaced; 0 = all)."""
    threads: int = 0
    """torch CPU threads (0: the source run's setting)."""
    progress: bool = True
    """Show progress bars."""


class CompactError(UserError):
    """The compacted run cannot be written as asked."""


def check_args(args: CompactArgs) -> None:
    """Refuse impossible settings and an existing output, before any work."""
    if not 0.0 < args.keep_fraction <= 1.0:
        raise ConfigError(f"--keep-fraction {args.keep_fraction}: expected a fraction 0 < f <= 1")
    for flag, value in (("--finetune-steps", args.finetune_steps), ("--eval-train-views", args.eval_train_views),
                        ("--threads", args.threads)):
        if value < 0:
            raise ConfigError(f"{flag} {value}: must be >= 0")
    if not args.run_dir.is_dir():
        raise CompactError(f"{args.run_dir}: no such run directory")
    if args.output.exists():
        raise CompactError(f"--output {args.output}: exists; choose a new run directory")
    if args.output.resolve() == args.run_dir.resolve():
        raise CompactError(f"--output {args.output}: is the source run")


def with_flags(argv: list[str], values: dict[str, str]) -> list[str]:
    """``argv`` without the flags ``SET_BY_COMPACT`` (as ``--flag value`` or ``--flag=value``,
    dashes or underscores) and with ``values`` ({flag: value}) appended."""
    def norm(token: str) -> str:
        return token.split("=", 1)[0].replace("_", "-")

    out, i = [], 0
    while i < len(argv):
        flag = norm(argv[i])
        if flag in SET_BY_COMPACT:
            i += 1 if "=" in argv[i] else 2
            continue
        out.append(argv[i])
        i += 1
    for flag, value in values.items():
        out += [flag, value]
    return out


def summary(evaluation: dict, checkpoint: Optional[Path]) -> dict:
    """The figures compact reports for one state: Gaussians, checkpoint bytes, render speed and PSNR."""
    nvs = evaluation.get("novel_view") or {}
    rec = evaluation.get("reconstruction") or {}
    return {"step": evaluation["step"], "num_gaussians": evaluation["num_gaussians"],
            "checkpoint_bytes": None if checkpoint is None else checkpoint.stat().st_size,
            "render_fps": nvs.get("render_fps", rec.get("render_fps")),
            "nvs_psnr": nvs.get("psnr"), "nvs_ssim": nvs.get("ssim"), "train_psnr": rec.get("psnr")}


def format_table(rows: dict[str, dict]):
    from rich.table import Table

    table = Table(title="omnire compact")
    for col in ("state", "step", "Gaussians", "checkpoint MB", "render fps", "NVS PSNR", "NVS SSIM", "train PSNR"):
        table.add_column(col)

    def f(v, fmt):
        return "-" if v is None or v != v else format(v, fmt)

    for name, r in rows.items():
        mb = None if r["checkpoint_bytes"] is None else r["checkpoint_bytes"] / 1e6
        table.add_row(name, str(r["step"]), str(r["num_gaussians"]), f(mb, ".1f"), f(r["render_fps"], ".2f"),
                      f(r["nvs_psnr"], ".2f"), f(r["nvs_ssim"], ".3f"), f(r["train_psnr"], ".2f"))
    return table


def main(argv: list[str], plugins) -> int:
    from omnire.command_api import output_console

    args = tyro.cli(CompactArgs, args=argv, prog="omnire compact")
    check_args(args)
    console = output_console()
    t0 = time.perf_counter()
    source = Reconstruction.from_run(args.run_dir, plugins, args.checkpoint, read_only=True)
    config, scene, source_ckpt, info = source.config, source.scene, source.checkpoint, source.run_info
    step = source.step
    del source  # only its configuration, scene and checkpoint path are needed
    output = args.output.resolve()
    partial = output.parent / f".{output.name}.partial"
    if partial.exists():
        raise CompactError(f"{partial}: left by an interrupted compact; remove it first")
    max_steps = max(1, step + args.finetune_steps)
    trainer_config = dataclasses.replace(
        config.trainer, resume=source_ckpt, output_dir=output.parent, run_name=partial.name, max_steps=max_steps,
        max_seconds=0.0, eval_every=0, checkpoint_every=max_steps, eval_train_views=args.eval_train_views,
        threads=args.threads or config.trainer.threads, progress=args.progress, observers=())
    recorded = with_flags(info.argv, {"--trainer.output-dir": str(output.parent), "--trainer.run-name": output.name,
                                      "--trainer.max-steps": str(max_steps)})
    try:
        trainer = Trainer(dataclasses.replace(config, trainer=trainer_config), plugins, argv=recorded, scene=scene)
        evaluations, counts = compact(trainer, args, console)
        checkpoints = {"source": source_ckpt, "compacted": trainer.run.checkpoint_path(trainer.step)}
        rows = {state: summary(ev, checkpoints.get(state)) for state, ev in evaluations.items()}
        report = {"source_run": str(args.run_dir.resolve()), "source_checkpoint": str(source_ckpt),
                  "keep_fraction": args.keep_fraction, "finetune_steps": args.finetune_steps,
                  "counts": {n: {"before": b, "after": a} for n, (b, a) in counts.items()},
                  "seconds": time.perf_counter() - t0, "states": rows}
        run = RunDirectory(partial)
        run_info = run.read_info()
        run_info.extra["compacted_from"] = {k: report[k] for k in ("source_run", "source_checkpoint", "keep_fraction",
                                                                   "finetune_steps", "counts")}
        atomic_write_text(run.info_path, run_info.to_json())
        atomic_write_text(partial / "compact.json", json.dumps(report, indent=2))
        os.rename(partial, output)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    console.print(format_table(rows))
    console.print(f"wrote {output} ({sum(b for b, _ in counts.values())} -> {sum(a for _, a in counts.values())} "
                  f"Gaussians) in {time.perf_counter() - t0:.0f} s")
    return 0


def compact(trainer: Trainer, args: CompactArgs, console) -> tuple[dict[str, dict], dict[str, tuple[int, int]]]:
    """Evaluate, prune, (fine-tune,) checkpoint and evaluate ``trainer``'s run. Returns the
    evaluations by state (source, pruned when fine-tuned, compacted) and the per-node
    Gaussian counts before and after pruning."""
    from rich.progress import Progress

    from omnire.api import prune_nodes

    evaluations = {"source": trainer.evaluate(write=False)}
    with Progress(console=console, transient=True, disable=not args.progress) as bar:
        task = bar.add_task("contribution", total=trainer.contribution_sources())
        contributions = trainer.training_contributions(progress=lambda: bar.advance(task))
    counts = prune_nodes(trainer, contributions, args.keep_fraction)
    if args.finetune_steps:
        evaluations["pruned"] = trainer.evaluate(write=False)
        evaluations["compacted"] = trainer.train()  # checkpoints and evaluates at its end
    else:
        trainer.write_run_info()
        trainer.save_checkpoint()
        evaluations["compacted"] = trainer.evaluate()
    return evaluations, counts
