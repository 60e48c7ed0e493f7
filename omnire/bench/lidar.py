"""``omnire bench lidar``: methods with LiDAR learning against the two LiDAR baselines.

``omnire bench train`` with ``--method.lidar.enabled`` added to every method (its options,
its subprocess per method, its ``results.json``; omnire/bench/train.py): the trainer's
periodic evaluation scores the held-out sweeps (omnire/lidar_evaluation.py) at each
checkpoint, so the depth error is known along the way.

Outputs in ``--output``: ``results.json``, ``results.md`` (the LiDAR figures of every method
on the held-out sweeps, then the nearest-training-sweep and mesh baselines, with the budget;
then bench train's camera table of the same runs), ``lidar_error_vs_time.png`` (median and
mean absolute range error against training time, baselines as horizontal lines) and each
method's run directory.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from omnire.bench.train import (TrainBenchArgs, budget_text, markdown_table, rasterizer_line, reporter, run_bench,
                               save_figure)
from omnire.lidar_evaluation import BASELINES, lidar_markdown_table

LIDAR_FLAG = "--method.lidar.enabled"


@dataclasses.dataclass
class LidarBenchArgs(TrainBenchArgs):
    """Train several methods with LiDAR learning on, one budget, one scene; compare their
    held-out sweeps with each other and with the two LiDAR baselines."""

    output: Path = Path("outputs/bench/lidar")
    """Output directory."""
    plot: bool = True
    """Write lidar_error_vs_time.png (needs matplotlib)."""


def lidar_table(results: list[dict], args: TrainBenchArgs) -> str:
    """``results.md``: the LiDAR table, the budget and scene, then bench train's table."""
    lines = [f"Scene: `{args.data}` ({args.dataparser} {args.dataparser_args}); budget per method: "
             f"{budget_text(args)}; every method trained with `{LIDAR_FLAG}`.", ""]
    rows = lidar_markdown_table(results)
    lines += rows or ["No method produced LiDAR figures (does the scene have LiDAR on held-out frames?)."]
    failed = [r["method"] for r in results if "final" not in r]
    if failed:
        lines += ["", "Failed: " + ", ".join(failed) + " (results.json holds their errors)."]
    lines += ["", rasterizer_line(results), "",
              "Held-out sweeps: the every-10th frames (as the cameras), each on its beam grid (missing returns "
              "included); range errors over the recorded returns the renderer gives a range, ray drop at p > 0.5, "
              "Chamfer over the points predicted to return (docs/lidar.md, \"Evaluation on held-out sweeps\").",
              "", "## Cameras of the same runs", "", markdown_table(results, args, with_lidar=False)]
    return "\n".join(lines) + "\n"


def plot(results: list[dict], path: Path) -> None:
    """Median and mean absolute range error on the held-out sweeps against training time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=110)
    first = next((r["final"] for r in results if "lidar.sweeps" in r.get("final", {})), {})
    for ax, (stat, title) in zip(axes, [("median", "median"), ("mean", "mean")]):
        key = f"{stat}_abs_range_error"
        for r in results:
            curve = [c for c in r.get("curve", []) if c.get(f"lidar.{key}") is not None and c[f"lidar.{key}"] == c[f"lidar.{key}"]]
            if curve:
                ax.plot([c["train_seconds"] for c in curve], [c[f"lidar.{key}"] for c in curve], "o-", label=r["method"])
        for (name, label), style in zip(BASELINES, ("--", ":")):
            value = first.get(f"lidar_baselines.{name}.{key}")
            if value is not None and value == value:
                ax.axhline(value, color="grey", ls=style, label=label)
        ax.set_title(f"held-out sweeps: {title} |range error|")
        ax.set_xlabel("training time (s, evaluation excluded)")
        ax.set_ylabel("metres")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    save_figure(fig, axes, path)


def main(argv: list[str], plugins) -> int:
    return run_bench(LidarBenchArgs, argv, plugins, "omnire bench lidar",
                     reporter(lidar_table, plot, "lidar_error_vs_time.png"), extra_method_args=LIDAR_FLAG)
