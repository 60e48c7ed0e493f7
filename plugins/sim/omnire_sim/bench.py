"""``omnire bench render RUN [RUN ...]``: rendering speed of trained runs.

Each run is measured in its own subprocess (so its peak resident memory is its own): it is
loaded with ``Reconstruction.from_run``, then its recorded views (held-out frames, topped up
with training frames to ``--views``, evenly spread) are rendered at every ``--resolutions``
size through the run's own rasterizer, after ``--warmup`` untimed renders. Reported per run
and size: frames per second (views / total render time), the median time per frame, the
Gaussians in the scene, and the process's peak resident memory.

``--rig`` renders every camera of each chosen view's frame together, through
``Reconstruction.render_cameras`` as ``omnire sim`` and the render server draw a frame (fps
then counts images, and the median is per image).

``--save-images DIR`` keeps every render (float32 .npy) and ``--compare-to DIR`` reports the
largest absolute pixel difference against such a set (same runs, views and sizes): a
speed-up must not change the pixels. ``--training-path`` renders with autograd on through the
plain torch composition (culling, concatenation, torch SH and activations, then the
rasterizer: how every render was drawn before the no-grad inference path of
``SceneModel.render_parts`` existed): the reference the inference path is compared with.

Every run and size also reports where a render's time goes (``stages_ms``, the second
table): the mean of the stages the render measured (``RenderResult.timings``: node
evaluation, the rasterizer's own stages, the rest of the rasterizer call, the environment
(sky) and exposure), what the render spent outside them, and with ``--profile`` the
conversion of the image to 8 bits and PNG (``omnire.api.write_png``, as ``omnire sim``
writes frames). ``sky_fraction``: the mean share of the pixels at which the environment
(sky) was evaluated (``RenderResult.environment_pixels``; renders without autograd skip the
pixels the Gaussians cover).
"""
from __future__ import annotations

import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np
import tyro

from omnire.api import ConfigError, Plugins, PluginSelection, atomic_write_text


@dataclasses.dataclass
class BenchRenderArgs:
    """Frames per second and peak memory when rendering trained runs."""

    runs: tyro.conf.Positional[tuple[Path, ...]]
    """Run directories (e.g. trained 3dgs, streetgs and omnire runs of one scene)."""
    resolutions: tuple[str, ...] = ("480x270", "960x540")
    """Image sizes WIDTHxHEIGHT (the cameras' intrinsics are scaled)."""
    views: int = 12
    """Views rendered per run and size (held-out frames first, then training frames)."""
    warmup: int = 2
    """Untimed renders before timing."""
    threads: int = 2
    """Torch / rasterizer threads."""
    output: Path = Path("outputs/bench/render")
    """Where results.json and results.md are written."""
    save_images: Optional[Path] = None
    """Keep every render as float32 .npy under this directory (a reference for --compare-to)."""
    compare_to: Optional[Path] = None
    """Report the largest absolute pixel difference against renders saved by --save-images."""
    training_path: bool = False
    """Render with autograd on through the plain torch composition instead of the inference path: a reference for --compare-to."""
    profile: bool = False
    """Also time writing each render as an 8-bit PNG (a stage of the profile table)."""
    rig: bool = False
    """Render every camera of each chosen view's frame together (``Reconstruction.render_cameras``, as omnire sim and the render server draw a frame): fps counts images; no stage table."""


STAGE_COLUMNS = (("nodes", "nodes"), ("raster.rows", "rows"), ("raster.depth_order", "depth order"),
                 ("raster.binning", "binning"), ("raster.compositing", "compositing"),
                 ("raster.other", "raster other"), ("environment", "sky + exposure"), ("other", "other"),
                 ("png", "PNG"))
"""The profile table's stages (``stages_ms`` keys) and their column names."""


def stage_times(timings: dict[str, float], total: float) -> dict[str, float]:
    """Seconds per stage of one render from its ``RenderResult.timings`` and its wall time
    ``total``: the rasterizer's unmeasured rest as ``raster.other``, the render's as ``other``."""
    out = dict(timings)
    if "raster" in out:
        inner = sum(v for k, v in out.items() if k.startswith("raster."))
        out["raster.other"] = out.pop("raster") - inner
        out["other"] = total - inner - out["raster.other"] - out.get("nodes", 0.0) - out.get("environment", 0.0)
    return out


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--resolutions {text!r}: expected WIDTHxHEIGHT, e.g. 480x270") from None
    if w <= 0 or h <= 0:
        raise ConfigError(f"--resolutions {text!r}: sizes must be positive")
    return w, h


def pick_views(scene, count: int) -> list:
    """Up to ``count`` recorded views: held-out frames first, then training frames, each
    group evenly spread over the log."""
    test, train = scene.views(scene.test_frames), scene.views(scene.train_frames)
    chosen = test[:: max(1, len(test) // max(1, count))][:count] if test else []
    if len(chosen) < count and train:
        rest = count - len(chosen)
        idx = np.linspace(0, len(train) - 1, min(rest, len(train))).round().astype(int)
        chosen += [train[i] for i in idx]
    return chosen


def measure(run: Path, plugins: Plugins, sizes: list[tuple[int, int]], views: int, warmup: int, threads: int,
            save: Optional[Path], compare: Optional[Path], training_path: bool = False, profile: bool = False,
            rig: bool = False) -> dict:
    """Render ``run`` at every size (in this process); see the module docstring."""
    import torch

    from omnire.api import Reconstruction, View, write_png

    torch.set_num_threads(threads)
    recon = Reconstruction.from_run(run, plugins)
    chosen = pick_views(recon.scene, views)
    out = {"run": str(run), "method": recon.run_info.method, "rasterizer": recon.rasterizer_name,
           "gaussians": recon.num_gaussians(), "step": recon.step, "views": len(chosen), "sizes": {}}
    key = run.resolve().name
    out["path"] = "training" if training_path else "inference"
    if training_path:  # the plain torch composition (assemble + composite), not the fused native one
        recon.use_fused_training = False
    shots = [[v] for v in chosen]  # the views rendered together: one each, or a rig's cameras per frame
    if rig:
        frames = list(dict.fromkeys(v.frame for v in chosen))
        shots = [[View(camera=c, frame=f) for c in range(len(recon.scene.cameras))] for f in frames]
    out["views"] = sum(len(shot) for shot in shots)
    out["rig"] = rig
    with torch.set_grad_enabled(training_path):
        for w, h in sizes:
            lenses = [[recon.camera(v).resized(w, h) for v in shot] for shot in shots]
            for shot, cams in list(zip(shots, lenses))[:warmup]:
                recon.render_cameras(cams, recon.time(shot[0].frame))
            times, stages, diff, sky = [], [], 0.0, []
            for shot, cams in zip(shots, lenses):
                t0 = time.perf_counter()
                results = recon.render_cameras(cams, recon.time(shot[0].frame))
                times.append((time.perf_counter() - t0) / len(shot))
                for v, result in zip(shot, results):
                    sky.append(result.environment_pixels / (w * h))
                    if not rig:  # a render's stages add up to its time only when it renders alone
                        stages.append(stage_times(result.timings, times[-1]))
                    rgb = result.rgb
                    if profile and not rig:
                        with tempfile.TemporaryDirectory() as tmp:
                            t0 = time.perf_counter()
                            write_png(Path(tmp) / "frame.png", rgb)
                            stages[-1]["png"] = time.perf_counter() - t0
                    name = f"{key}/{w}x{h}/{recon.scene.cameras[v.camera].name}_{v.frame:04d}.npy"
                    img = rgb.detach().cpu().numpy().astype(np.float32)
                    if save is not None:
                        (save / name).parent.mkdir(parents=True, exist_ok=True)
                        np.save(save / name, img)
                    if compare is not None:
                        ref = compare / name
                        if not ref.is_file():
                            raise ConfigError(f"--compare-to: {ref} missing (save it first with --save-images)")
                        diff = max(diff, float(np.abs(np.load(ref) - img).max()))
            images = sum(len(shot) for shot in shots)
            names = sorted({k for st in stages for k in st})
            out["sizes"][f"{w}x{h}"] = {"fps": images / sum(t * len(shot) for t, shot in zip(times, shots)),
                                       "median_ms": 1000 * float(np.median(times)),
                                       "max_abs_diff": diff if compare is not None else None,
                                       "sky_fraction": float(np.mean(sky)),
                                       "stages_ms": {k: 1000 * float(np.mean([st.get(k, 0.0) for st in stages]))
                                                     for k in names}}
    out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def format_table(results: list[dict]) -> str:
    rows = ["| Run | Method | Gaussians | Size | Views | fps | ms / frame | peak MB | max abs diff |",
            "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        for size, s in r["sizes"].items():
            diff = "-" if s["max_abs_diff"] is None else f"{s['max_abs_diff']:.2e}"
            views = f"{r['views']} (rig)" if r.get("rig") else str(r["views"])
            rows.append(f"| {Path(r['run']).name} | {r['method']} | {r['gaussians']} | {size} | {views} | "
                        f"{s['fps']:.2f} | {s['median_ms']:.1f} | {r['peak_mb']:.0f} | {diff} |")
    return "\n".join(rows) + "\n"


def format_profile(results: list[dict]) -> str:
    """The mean ms per stage of every run and size (:data:`STAGE_COLUMNS`; '-' where not measured)."""
    rows = ["| Run | Size | " + " | ".join(name for _, name in STAGE_COLUMNS) + " | total |",
            "|---|---|" + "---|" * (len(STAGE_COLUMNS) + 1)]
    for r in results:
        for size, s in r["sizes"].items():
            ms = s.get("stages_ms", {})
            cells = [f"{ms[k]:.1f}" if k in ms else "-" for k, _ in STAGE_COLUMNS]
            rows.append(f"| {Path(r['run']).name} | {size} | " + " | ".join(cells) + f" | {1000.0 / s['fps']:.1f} |")
    return "\n".join(rows) + "\n"


def main(argv: list[str], plugins) -> int:
    from omnire.command_api import output_console

    args = tyro.cli(BenchRenderArgs, args=argv, prog="omnire bench render")
    sizes = [parse_size(s) for s in args.resolutions]
    if not args.runs:
        raise ConfigError("give at least one run directory")
    for run in args.runs:
        if not (run / "run.json").is_file():
            raise ConfigError(f"{run}: not a run directory (no run.json)")
    if args.views <= 0 or args.warmup < 0 or args.threads <= 0:
        raise ConfigError("--views and --threads must be > 0, --warmup >= 0")
    console = output_console()
    results = []
    for run in args.runs:
        with tempfile.TemporaryDirectory() as tmp:
            result_file = Path(tmp) / "result.json"
            spec = {"run": str(run), "sizes": sizes, "views": args.views, "warmup": args.warmup,
                    "threads": args.threads, "save": str(args.save_images) if args.save_images else None,
                    "compare": str(args.compare_to) if args.compare_to else None, "result": str(result_file),
                    "training_path": args.training_path, "profile": args.profile, "rig": args.rig,
                    "plugins": plugins.selection.as_dict()}
            env = dict(os.environ, OMP_NUM_THREADS=str(args.threads))
            proc = subprocess.run([sys.executable, "-m", "omnire_sim.bench", json.dumps(spec)], env=env,
                                  capture_output=True, text=True)
            if proc.returncode != 0 or not result_file.is_file():
                tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-5:])
                raise ConfigError(f"{run}: rendering benchmark failed:\n{tail}")
            results.append(json.loads(result_file.read_text()))
        console.print(f"{run}: " + ", ".join(f"{k} {v['fps']:.2f} fps" for k, v in results[-1]["sizes"].items()))
    args.output.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.output / "results.json", json.dumps(results, indent=1) + "\n")
    table = format_table(results) + "\nms per render by stage (means over the views; total: the mean render, PNG not included):\n\n" + \
        format_profile(results)
    atomic_write_text(args.output / "results.md", table)
    console.print(table)
    return 0


def _worker(spec_json: str) -> None:
    spec = json.loads(spec_json)
    plugins = PluginSelection.from_dict(spec["plugins"]).load()  # the same plugin set as the command's
    result = measure(Path(spec["run"]), plugins, [tuple(s) for s in spec["sizes"]], spec["views"], spec["warmup"],
                     spec["threads"], Path(spec["save"]) if spec["save"] else None,
                     Path(spec["compare"]) if spec["compare"] else None, spec["training_path"], spec["profile"],
                     spec["rig"])
    atomic_write_text(spec["result"], json.dumps(result))


if __name__ == "__main__":
    _worker(sys.argv[1])
