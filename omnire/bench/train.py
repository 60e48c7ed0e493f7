"""``omnire bench train``: methods against each other, run time against error.

Every method trains on the same scene (same frames, resolution, split) with the same step
budget (optionally also a wall-clock budget), each in its own ``omnire train`` subprocess so
peak memory is per method and one crash does not stop the others. Along the way the trainer
evaluates at evenly spaced checkpoints, recording training wall time (evaluation excluded),
PSNR / SSIM (full, human, vehicle; reconstruction and novel view), depth RMSE / Chamfer,
Gaussian count, training it/s and rendering frames/s.

Outputs in ``--output``: ``results.json`` (everything), ``results.md`` (a table in the
paper's layout with the budget and the copy-nearest-frame baseline), ``psnr_vs_time.png``
(novel-view PSNR against training time per method), and each method's run directory.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import tyro

from omnire.bench.machine import machine_info
from omnire.io.atomic import atomic_write_text
from omnire.lidar_evaluation import lidar_markdown_table
from omnire.rundir import RunDirectory


@dataclasses.dataclass
class TrainBenchArgs:
    """Train several methods with one budget on one scene and compare them."""

    dataparser: Optional[str] = None
    """Dataparser name (``omnire plugins`` lists them), e.g. pandaset; required unless --report-only."""
    data: Optional[Path] = None
    """Scene directory, e.g. data/demo/pandaset_002; required unless --report-only."""
    methods: tuple[str, ...] = ()
    """Methods to compare (default: every registered method). An entry may be a variant
    ``LABEL=METHOD [FLAGS]``, e.g. "omnire-no-smpl=omnire --method.disable smpl" (ablations)."""
    dataparser_args: str = "--scale 1.0"
    """Extra dataparser flags as one string, identical for every method: --dataparser-args="--scale 0.5"."""
    method_args: str = ""
    """Extra flags for every method as one string: --method-args="--method.rasterizer cpu"."""
    steps: int = 2000
    """Step budget per method, which the schedules span (0: none; --seconds alone then lays
    the default schedule over the time budget, omnire/schedule.py)."""
    seconds: float = 0.0
    """Training-time budget per method (0: none). With --steps, training ends at whichever
    is spent first and the schedules fit it (the larger of the two fractions spent)."""
    checkpoints: int = 4
    """Evaluations along the way (evenly spaced steps; with --steps 0 only the final one)."""
    threads: int = 0
    """torch threads per run (0: default)."""
    output: Path = Path("outputs/bench/train")
    """Output directory."""
    plot: bool = True
    """Write psnr_vs_time.png (needs matplotlib)."""
    report_only: bool = False
    """Train nothing: rewrite results.md and the plot from the results.json in --output."""
    reuse: bool = False
    """Keep the results already in --output/results.json of entries whose exact training command
    (scene, budget, flags) succeeded before; train only the others (continue an interrupted
    comparison, or add methods to one)."""


def parse_entry(entry: str) -> tuple[str, str, list[str]]:
    """A ``--methods`` entry -> (label, method, extra flags): "3dgs" or "LABEL=METHOD [FLAGS]"."""
    label, sep, rest = entry.partition("=")
    if not sep:
        return entry, entry, []
    tokens = shlex.split(rest)
    if not label.strip() or not tokens or "/" in label:
        raise ValueError(f"--methods entry {entry!r}: expected METHOD or LABEL=METHOD [FLAGS] (label without '/')")
    return label.strip(), tokens[0], tokens[1:]


def _command(args: TrainBenchArgs, entry: str) -> list[str]:
    """The ``omnire train`` command line of one ``--methods`` entry."""
    label, method, flags = parse_entry(entry)
    steps = []
    if args.steps:
        steps = ["--trainer.max-steps", str(args.steps), "--trainer.checkpoint-every", str(args.steps),
                 "--trainer.eval-every", str(max(1, args.steps // max(1, args.checkpoints)))]
    return [sys.executable, "-m", "omnire.cli", "train", method, args.dataparser, "--data", str(args.data),
            *shlex.split(args.dataparser_args), *shlex.split(args.method_args), *flags,
            *steps, "--trainer.max-seconds", str(args.seconds),
            "--trainer.threads", str(args.threads), "--trainer.output-dir", str(args.output / "runs"),
            "--trainer.run-name", label, "--trainer.no-progress"]


def _run_method(args: TrainBenchArgs, entry: str) -> dict:
    label, method, flags = parse_entry(entry)
    run_dir = args.output / "runs" / label
    cmd = _command(args, entry)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, COLUMNS="200"))
    elapsed = time.perf_counter() - t0
    result = {"method": label, "base_method": method, "flags": flags, "command": cmd[2:], "exit_code": proc.returncode, "elapsed_s": elapsed}
    if proc.returncode != 0:
        result["error"] = (proc.stderr or proc.stdout)[-2000:]
        return result
    run = RunDirectory(run_dir)
    results = run.results()
    if results is None:
        result["error"] = f"{run.metrics_path}: no final evaluation recorded"
        return result
    result.update(results)
    result["rasterizer"] = run.read_info().extra.get("rasterizer")
    return result


def rasterizer_line(results: list[dict]) -> str:
    """One line under the table naming the rasterizer the runs used. Runs that used
    different ones (e.g. ``auto`` fell back to the torch rasterizer because the native one
    failed to build) are not a comparison of methods: the line says so, naming each."""
    used = {r["method"]: r.get("rasterizer") or "unrecorded" for r in results if "final" in r}
    kinds = sorted(set(used.values()))
    if len(kinds) <= 1:
        return f"Rasterizer: {kinds[0] if kinds else '-'} (every run)."
    return ("**Warning: the runs used different rasterizers, so their speeds (and any difference the "
            "rasterizers make) are not comparable**: " + ", ".join(f"{m}: {k}" for m, k in used.items()) + ".")


def _fmt(v, d=2) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}"


def budget_text(args: TrainBenchArgs) -> str:
    """``2000 steps``, ``600 s of training`` or ``3200 steps or 600 s of training``."""
    return " or ".join(([f"{args.steps} steps"] if args.steps else [])
                       + ([f"{args.seconds:.0f} s of training"] if args.seconds else []))


def markdown_table(results: list[dict], args: TrainBenchArgs, with_lidar: bool = True) -> str:
    """The comparison in the paper's layout (the copy-nearest-frame baseline, the rasterizer,
    a same-step table when a time budget stopped methods apart, variants) and, with
    ``with_lidar``, the LiDAR table of the methods that learned LiDAR."""
    budget = budget_text(args)
    lines = [
        f"Scene: `{args.data}` ({args.dataparser} {args.dataparser_args}); budget per method: {budget}; "
        f"same frames, resolution and split for every method.",
        "",
        "| Method | Recon PSNR | Recon SSIM | Recon human PSNR | Recon vehicle PSNR | NVS PSNR | NVS SSIM | "
        "NVS human PSNR | NVS vehicle PSNR | Depth RMSE (m) | Chamfer (m) | Gaussians | train it/s | render fps | "
        "peak MB | train s | steps |",
        "|" + "---|" * 17,
    ]
    copy = None
    for r in results:
        if "final" not in r:
            lines.append(f"| {r['method']} | failed (exit {r['exit_code']}) |" + " |" * 15)
            continue
        f = r["final"]
        copy = copy or f
        lines.append("| " + " | ".join([
            r["method"], _fmt(f.get("reconstruction.full_psnr")), _fmt(f.get("reconstruction.full_ssim"), 3),
            _fmt(f.get("reconstruction.human_psnr")), _fmt(f.get("reconstruction.vehicle_psnr")),
            _fmt(f.get("novel_view.full_psnr")), _fmt(f.get("novel_view.full_ssim"), 3),
            _fmt(f.get("novel_view.human_psnr")), _fmt(f.get("novel_view.vehicle_psnr")),
            _fmt(f.get("novel_view.depth_rmse")), _fmt(f.get("novel_view.depth_chamfer"), 3),
            str(f.get("num_gaussians", "-")), _fmt(r.get("train_its")), _fmt(f.get("novel_view.render_fps")),
            _fmt(f.get("peak_rss_mb"), 0), _fmt(f.get("train_seconds"), 0), str(r.get("steps_done", "-"))]) + " |")
    if copy:
        lines.append("| copy nearest training frame | - | - | - | - | " + " | ".join([
            _fmt(copy.get("novel_view.copy_full_psnr")), _fmt(copy.get("novel_view.copy_full_ssim"), 3),
            _fmt(copy.get("novel_view.copy_human_psnr")), _fmt(copy.get("novel_view.copy_vehicle_psnr"))])
            + " | - | - | - | - | - | - | - | - |")
    lines += ["", rasterizer_line(results)]
    lines += _same_step_table(results)
    lidar = lidar_markdown_table(results) if with_lidar else []
    if lidar:
        lines += ["", "LiDAR on the held-out sweeps (methods trained with --method.lidar.enabled; the baselines "
                  "need no training, docs/lidar.md):", "", *lidar]
    variants = [r for r in results if r.get("flags") or r.get("base_method", r["method"]) != r["method"]]
    if variants:
        lines += ["", "Variants: " + "; ".join(f"{r['method']} = `{r['base_method']} {shlex.join(r['flags'])}`"
                                           for r in variants) + "."]
    lines += ["", "Depth metrics are on held-out frames. NVS = novel view synthesis on the held-out frames "
              "(every 10th frame, all cameras)."]
    return "\n".join(lines) + "\n"


def common_step(results: list[dict]) -> Optional[int]:
    """The largest evaluated step every successful method reached (None if there is none)."""
    steps = [{c["step"] for c in r.get("curve", [])} for r in results if "final" in r]
    shared = set.intersection(*steps) if steps else set()
    return max(shared) if shared else None


def _same_step_table(results: list[dict]) -> list[str]:
    """When a wall-clock budget stopped some methods early, the same metrics for every method
    at the last evaluated step all of them reached: an equal-iteration comparison (all
    methods share the schedule of the step budget, so step S is the same point of it)."""
    done = [r for r in results if "final" in r]
    step = common_step(done)
    if step is None or all(r.get("steps_done") == step for r in done):
        return []
    lines = ["", f"Same iteration budget: every method at step {step} (the last evaluation all of them reached).", "",
             "| Method | Recon PSNR | Recon human PSNR | Recon vehicle PSNR | NVS PSNR | NVS SSIM | NVS human PSNR | "
             "NVS vehicle PSNR | Depth RMSE (m) | Gaussians | train s |",
             "|" + "---|" * 11]
    for r in done:
        c = next(c for c in r["curve"] if c["step"] == step)
        lines.append("| " + " | ".join([
            r["method"], _fmt(c.get("reconstruction.full_psnr")), _fmt(c.get("reconstruction.human_psnr")),
            _fmt(c.get("reconstruction.vehicle_psnr")), _fmt(c.get("novel_view.full_psnr")),
            _fmt(c.get("novel_view.full_ssim"), 3), _fmt(c.get("novel_view.human_psnr")),
            _fmt(c.get("novel_view.vehicle_psnr")), _fmt(c.get("novel_view.depth_rmse")),
            str(c.get("num_gaussians", "-")), _fmt(c.get("train_seconds"), 0)]) + " |")
    return lines


def plot(results: list[dict], path: Path) -> None:
    """Novel-view PSNR against training time per method: full image, human and vehicle regions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("full", "full image"), ("human", "human regions"), ("vehicle", "vehicle regions")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), dpi=110)
    for ax, (region, title) in zip(axes, panels):
        key = f"novel_view.{region}_psnr"
        for r in results:
            curve = [c for c in r.get("curve", []) if c.get(key) is not None and c[key] == c[key]]
            if curve:
                ax.plot([c["train_seconds"] for c in curve], [c[key] for c in curve], "o-", label=r["method"])
        copy = next((r["final"].get(f"novel_view.copy_{region}_psnr") for r in results if "final" in r), None)
        if copy is not None and copy == copy:
            ax.axhline(copy, color="grey", ls="--", label="copy nearest frame")
        ax.set_title(f"novel views, {title}")
        ax.set_xlabel("training time (s, evaluation excluded)")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    save_figure(fig, axes, path)


def save_figure(fig, axes, path: Path) -> None:
    """A benchmark's figure, legend in its first panel, written to ``path`` (PNG) atomically."""
    import matplotlib.pyplot as plt

    axes[0].legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)


def main(argv: list[str], plugins) -> int:
    return run_bench(TrainBenchArgs, argv, plugins, "omnire bench train",
                     reporter(markdown_table, plot, "psnr_vs_time.png"))


def run_bench(args_type: type, argv: list[str], plugins, prog: str, report, extra_method_args: str = "") -> int:
    """Parse ``argv`` as ``args_type`` (:class:`TrainBenchArgs` or a subclass), train every
    ``--methods`` entry (``extra_method_args`` appended to ``--method-args``), keep
    ``results.json`` current after each, and hand the results to ``report(args, results,
    console)``; ``--report-only`` reports from the saved results.json."""
    from rich.console import Console

    args = tyro.cli(args_type, args=argv, prog=prog)
    console = Console()
    if args.report_only:
        path = args.output / "results.json"
        if not path.is_file():
            console.print(f"[red]error:[/] {path}: no results.json to report from (run without --report-only first)")
            return 2
        saved = json.loads(path.read_text())
        # results.json stores JSON scalars; give them back the fields' types (data is a path).
        kinds = {"data": Path, "dataparser": str, "dataparser_args": str, "steps": int, "seconds": float}
        kept = {k: (None if v is None else kinds[k](v)) for k, v in saved["args"].items() if k in kinds}
        return report(dataclasses.replace(args, **kept), saved["results"], console)
    from omnire.errors import ConfigError

    if args.dataparser is None or args.data is None:
        raise ConfigError(f"{prog}: --dataparser and --data are required (e.g. --dataparser pandaset "
                          "--data data/demo/pandaset_002)")
    if args.steps < 0 or args.seconds < 0 or not (args.steps or args.seconds > 0):
        raise ConfigError(f"{prog}: --steps {args.steps} --seconds {args.seconds}: expected a step "
                          "budget, a time budget or both (>= 0, not both 0)")
    if extra_method_args:
        args = dataclasses.replace(args, method_args=f"{args.method_args} {extra_method_args}".strip())
    methods = list(args.methods) or plugins.methods.names()
    try:
        labels = [parse_entry(m)[0] for m in methods]
    except ValueError as e:
        console.print(f"[red]error:[/] {e}")
        return 2
    if len(set(labels)) != len(labels):
        console.print(f"[red]error:[/] --methods: labels must be unique, got {labels}")
        return 2
    args.output.mkdir(parents=True, exist_ok=True)
    previous: dict[tuple[str, ...], dict] = {}
    if args.reuse and (args.output / "results.json").is_file():
        previous = {tuple(r["command"]): r for r in json.loads((args.output / "results.json").read_text())["results"]
                    if r.get("exit_code") == 0}
    results = []
    machine = machine_info(args.threads)
    for m in methods:
        kept = previous.get(tuple(_command(args, m)[2:]))
        if kept is not None:
            console.print(f"[bold]{m}[/]: reusing the earlier result (same command)")
            results.append(kept)
        else:
            console.print(f"[bold]{m}[/]: training ({budget_text(args)})...")
            r = _run_method(args, m)
            results.append(r)
            status = "ok" if r["exit_code"] == 0 else f"FAILED: {r.get('error', '')[-300:]}"
            console.print(f"  {m}: {status} in {r['elapsed_s']:.0f} s" + (f" ({r['rasterizer']} rasterizer)" if r.get("rasterizer") else ""))
            mixed = rasterizer_line(results)
            if mixed.startswith("**Warning"):  # say it as soon as it happens, not only in the table
                console.print(f"[yellow]{mixed}[/] (pass --method-args=\"--method.rasterizer cpu\" to fail instead)")
        # after every entry, reused ones included: an interrupted comparison keeps what it has
        atomic_write_text(args.output / "results.json", json.dumps(
            {"args": json.loads(json.dumps(dataclasses.asdict(args), default=str)), "machine": machine,
             "results": results}, indent=2))
    return report(args, results, console)


def reporter(table_of, plot_of, plot_name: str):
    """The ``report`` of :func:`run_bench`: ``table_of(results, args)`` written to
    results.md and printed, ``plot_of(results, path)`` to ``plot_name`` unless --no-plot;
    exit status 1 when a method failed."""

    def report(args: TrainBenchArgs, results: list[dict], console) -> int:
        table = table_of(results, args)
        atomic_write_text(args.output / "results.md", table)
        if args.plot:
            plot_of(results, args.output / plot_name)
        console.print(table)
        return 0 if all(r["exit_code"] == 0 for r in results) else 1

    return report
