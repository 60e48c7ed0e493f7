"""Gathering job results: ``results.json``, ``results.md`` and plots, as ``omnire bench train`` does
for one scene, plus means and spread over scenes and seeds.

Per-scene tables and plots are ``omnire bench train``'s own (``markdown_table``, ``plot``);
the tables across scenes are built here.
"""
from __future__ import annotations

import json
import math
import os
import statistics
import warnings
from pathlib import Path
from typing import Optional

from omnire.api import atomic_write_text
from omnire.command_api import TrainBenchArgs, markdown_table, plot_train_bench as plot_scene

AGGREGATE_COLUMNS = [
    # (header, key in "final", decimals)
    ("NVS PSNR", "novel_view.full_psnr", 2),
    ("NVS SSIM", "novel_view.full_ssim", 3),
    ("NVS human PSNR", "novel_view.human_psnr", 2),
    ("NVS vehicle PSNR", "novel_view.vehicle_psnr", 2),
    ("Recon PSNR", "reconstruction.full_psnr", 2),
    ("Depth RMSE (m)", "novel_view.depth_rmse", 2),
    ("Gaussians", "num_gaussians", 0),
    ("train s", "train_seconds", 0),
]
COPY_COLUMNS = {"novel_view.full_psnr": "novel_view.copy_full_psnr", "novel_view.full_ssim": "novel_view.copy_full_ssim",
                "novel_view.human_psnr": "novel_view.copy_human_psnr",
                "novel_view.vehicle_psnr": "novel_view.copy_vehicle_psnr"}


def _num(v) -> Optional[float]:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def mean_std(values) -> tuple[Optional[float], Optional[float], int]:
    """Mean, sample standard deviation (None below two values) and count of the finite values."""
    vals = [x for x in (_num(v) for v in values) if x is not None]
    if not vals:
        return None, None, 0
    return statistics.fmean(vals), (statistics.stdev(vals) if len(vals) > 1 else None), len(vals)


def fmt_mean(values, decimals: int = 2) -> str:
    m, s, _ = mean_std(values)
    if m is None:
        return "-"
    return f"{m:.{decimals}f}" + (f" ± {s:.{decimals}f}" if s is not None else "")


def _order(values) -> list:
    seen: dict = {}
    for v in values:
        seen.setdefault(v, None)
    return list(seen)


def summary(results: list[dict]) -> dict:
    """Per method label: mean, std and n over its successful jobs (all scenes and seeds) of the
    final metrics; per scene: the copy-nearest-frame baseline. Goes into results.json."""
    out: dict = {"methods": {}, "copy_nearest_frame": {}}
    ok = [r for r in results if r.get("status") == "ok"]
    for label in _order(r["method"] for r in results):
        rows = [r["final"] for r in ok if r["method"] == label]
        out["methods"][label] = {"jobs": sum(r["method"] == label for r in results), "ok": len(rows), **{
            key: dict(zip(("mean", "std", "n"), mean_std(f.get(key) for f in rows))) for _, key, _ in AGGREGATE_COLUMNS}}
        gains = [_gain(r) for r in ok if r["method"] == label]
        out["methods"][label]["nvs_psnr_gain_over_copy"] = dict(zip(("mean", "std", "n"), mean_std(gains)))
    for scene in _order(r["scene"] for r in results):
        finals = [r["final"] for r in ok if r["scene"] == scene]
        out["copy_nearest_frame"][scene] = {copy: mean_std(f.get(copy) for f in finals)[0]
                                            for copy in COPY_COLUMNS.values()}
    return out


def _gain(r: dict) -> Optional[float]:
    a, b = _num(r["final"].get("novel_view.full_psnr")), _num(r["final"].get("novel_view.copy_full_psnr"))
    return a - b if a is not None and b is not None else None


def markdown(results: list[dict], meta: dict, plots: dict[str, str]) -> str:
    """The whole results.md: across scenes, per scene x method, failures, then each scene's
    ``omnire bench train`` table."""
    ok = [r for r in results if r.get("status") == "ok"]
    scenes = _order(r["scene"] for r in results)
    labels = _order(r["method"] for r in results)
    counts = {s: sum(r.get("status") == s for r in results) for s in ("ok", "failed", "interrupted")}
    not_run = len(results) - sum(counts.values())
    budget = f"{meta['steps']} steps" + (f" or {meta['seconds']:.0f} s of training" if meta.get("seconds") else "")
    seeds = meta.get("seeds", [])
    lines = [
        f"{len(results)} jobs: {counts['ok']} ok, {counts['failed']} failed, {counts['interrupted']} interrupted"
        + (f", {not_run} not run" if not_run else "") + f"; {len(scenes)} scenes x {len(labels)} methods/variants x "
        f"{len(seeds)} seeds ({', '.join(map(str, seeds))}); budget per job: {budget}.",
        "",
    ]
    if meta.get("command"):
        lines += ["```bash", meta["command"], "```", ""]
    lines += [
        "### Across scenes and seeds",
        "",
        "Mean ± sample standard deviation over every successful job of the method (all scenes and seeds); "
        "NVS = novel views (held-out frames). Gain = NVS PSNR minus copying the nearest training frame, per job.",
        "",
        "| Method | jobs ok | " + " | ".join(h for h, _, _ in AGGREGATE_COLUMNS) + " | NVS gain over copy (dB) |",
        "|" + "---|" * (len(AGGREGATE_COLUMNS) + 3),
    ]
    for label in labels:
        rows = [r for r in ok if r["method"] == label]
        total = sum(r["method"] == label for r in results)
        cells = [fmt_mean([r["final"].get(key) for r in rows], d) for _, key, d in AGGREGATE_COLUMNS]
        lines.append(f"| {label} | {len(rows)}/{total} | " + " | ".join(cells) + f" | {fmt_mean([_gain(r) for r in rows])} |")
    per_scene_copy = {s: next((r["final"] for r in ok if r["scene"] == s), None) for s in scenes}
    copy_cells = []
    for _, key, d in AGGREGATE_COLUMNS:
        copy = COPY_COLUMNS.get(key)
        copy_cells.append(fmt_mean([f.get(copy) for f in per_scene_copy.values() if f], d) if copy else "-")
    if any(per_scene_copy.values()):
        lines.append("| copy nearest training frame (over scenes) | - | " + " | ".join(copy_cells) + " | 0 |")
    lines += ["", "### Novel-view PSNR per scene", "",
              "Mean ± standard deviation over seeds; the last row copies the nearest training frame.", "",
              "| Method | " + " | ".join(scenes) + " | mean over scenes |", "|" + "---|" * (len(scenes) + 2)]
    for label in labels:
        per = [[r["final"].get("novel_view.full_psnr") for r in ok if r["method"] == label and r["scene"] == s]
               for s in scenes]
        scene_means = [mean_std(v)[0] for v in per]
        lines.append(f"| {label} | " + " | ".join(fmt_mean(v) for v in per) + f" | {fmt_mean(scene_means)} |")
    copy = [per_scene_copy[s].get("novel_view.copy_full_psnr") if per_scene_copy[s] else None for s in scenes]
    lines.append("| copy nearest training frame | " + " | ".join(fmt_mean([c]) for c in copy) + f" | {fmt_mean(copy)} |")
    if "all" in plots:
        lines += ["", f"![novel-view PSNR against training time, mean over scenes and seeds]({plots['all']})"]
    bad = [r for r in results if r.get("status") in ("failed", "interrupted")]
    if bad:
        lines += ["", "### Failed and interrupted jobs", ""]
        for r in bad:
            lines += [f"- `{r['job']}`: {r['status']} (exit {r.get('exit_code')}) on {r.get('node', '?')}, "
                      f"log `{r.get('log')}`", "", "  ```", *("  " + x for x in str(r.get("error", "")).splitlines()[-15:]),
                      "  ```"]
    lines += ["", "### Per scene"]
    multi_seed = len({r.get("seed") for r in results}) > 1
    for scene in scenes:
        rows = [r for r in results if r["scene"] == scene and r.get("status") in ("ok", "failed")]
        info = next((s for s in meta.get("scenes", []) if s["name"] == scene), {})
        lines += ["", f"#### {scene}", ""]
        if not rows:
            lines.append("No job of this scene has finished.")
            continue
        bench_rows = [dict(r, method=f"{r['method']} (seed {r['seed']})" if multi_seed else r["method"],
                           exit_code=r.get("exit_code")) for r in rows]
        args = TrainBenchArgs(dataparser=info.get("dataparser", "?"), data=Path(info.get("data", scene)),
                              dataparser_args=" ".join(info.get("args", [])), steps=meta["steps"],
                              seconds=meta.get("seconds", 0.0))
        lines.append(markdown_table(bench_rows, args).rstrip())
        if scene in plots:
            lines += ["", f"![{scene}: novel-view PSNR against training time]({plots[scene]})"]
    return "\n".join(lines) + "\n"


def plot_mean(results: list[dict], path: Path) -> None:
    """Novel-view PSNR against training time per method, mean over its successful jobs (scenes
    and seeds; for a region, those whose scene has it) at each evaluated step they all
    reached, ± one standard deviation shaded; the mean copy-nearest-frame baseline dashed.
    Panels: full image, human and vehicle regions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in results if r.get("status") == "ok" and r.get("curve")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), dpi=110)
    colours = {label: f"C{i % 10}" for i, label in enumerate(_order(r["method"] for r in ok))}
    for ax, region in zip(axes, ("full", "human", "vehicle")):
        key = f"novel_view.{region}_psnr"
        for label in colours:
            # jobs whose scene has this region (a highway has no humans)
            curves = [{c["step"]: c for c in r["curve"]} for r in ok
                      if r["method"] == label and _num(r["final"].get(key)) is not None]
            if not curves:
                continue
            steps = sorted(set.intersection(*(set(c) for c in curves)))
            xs, ms, ss = [], [], []
            for s in steps:
                m, sd, n = mean_std(c[s].get(key) for c in curves)
                if n == len(curves):
                    xs.append(statistics.fmean(c[s]["train_seconds"] for c in curves))
                    ms.append(m)
                    ss.append(sd or 0.0)
            if xs:
                ax.plot(xs, ms, "o-", color=colours[label], label=f"{label} (n={len(curves)})")
                ax.fill_between(xs, [m - s for m, s in zip(ms, ss)], [m + s for m, s in zip(ms, ss)],
                                color=colours[label], alpha=0.15)
        copy = mean_std({r["scene"]: r["final"].get(f"novel_view.copy_{region}_psnr") for r in ok}.values())[0]
        if copy is not None:
            ax.axhline(copy, color="grey", ls="--", label="copy nearest frame")
        ax.set_title(f"novel views, {region}{' image' if region == 'full' else ' regions'} (mean ± std)")
        ax.set_xlabel("training time (s, evaluation excluded)")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)


def write_report(output: Path, results: list[dict], meta: dict, plot: bool = True, warn=print) -> str:
    """Write results.json, results.md and (with matplotlib) psnr_vs_time.png plus one plot per
    scene under plots/; returns the markdown."""
    output = Path(output)
    write_results_json(output, results, meta)
    plots: dict[str, str] = {}
    if plot:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            warn("matplotlib is not installed: no plots (pip install matplotlib)")
            plot = False
    if plot and any(r.get("status") == "ok" for r in results):
        plot_mean(results, output / "psnr_vs_time.png")
        plots["all"] = "psnr_vs_time.png"
        multi_seed = len({r.get("seed") for r in results}) > 1
        for scene in _order(r["scene"] for r in results):
            rows = [dict(r, method=f"{r['method']} (seed {r['seed']})" if multi_seed else r["method"])
                    for r in results if r["scene"] == scene and r.get("status") == "ok"]
            if rows:
                (output / "plots").mkdir(parents=True, exist_ok=True)
                with warnings.catch_warnings():  # a scene without held-out frames has no curve to label
                    warnings.simplefilter("ignore", UserWarning)
                    plot_scene(rows, output / "plots" / f"{scene}.png")
                plots[scene] = f"plots/{scene}.png"
    text = markdown(results, meta, plots)
    atomic_write_text(output / "results.md", text)
    return text


def write_results_json(output: Path, results: list[dict], meta: dict) -> None:
    atomic_write_text(Path(output) / "results.json", json.dumps(
        {"args": meta, "results": results, "summary": summary(results)}, indent=2, default=str))
