"""``omnire bench raster``: forward / backward speed and peak memory of every rasterizer.

For each (rasterizer, Gaussian count, resolution) case a fresh Python subprocess builds the
same seeded random scene, renders ``warmup`` + ``repeats`` times and reports median forward
and backward milliseconds (backward = ``loss.backward()`` of a weighted sum of rgb, depth and
alpha, so every output's gradient path runs).

Peak extra memory (honest and process-isolated): in the child, after the scene is built and
the rasterizer constructed (extension loaded), we record the current RSS, reset the kernel's
peak-RSS counter (``echo 5 > /proc/self/clear_refs``), run all iterations, then read
``VmHWM``. Peak extra = VmHWM - baseline RSS, i.e. the largest resident growth during a
forward + backward, including torch's allocator caching and the autograd graph. If the
counter cannot be reset the value is an upper bound and the row says so.

Scenes: Gaussians uniformly spread over the view frustum at depths 2-40 m, log-normal
anisotropic scales whose median 1-sigma footprint s (pixels) is chosen so that
N * pi * (2 s)^2 = coverage * H * W (default coverage 8: each pixel inside the 2-sigma
ellipse of ~8 Gaussians), random rotations, opacities U(0.05, 0.95), RGB colours.

``--lidar`` times ``rasterize_lidar`` instead (the rasterizers declaring the ``lidar``
capability): each case is a Gaussian count x a beam grid BEAMSxAZIMUTHS (``--lidar-rays``,
default 64x1800: a Pandar64 revolution at 0.2 degrees, 115,200 rays, elevations evenly
spread over -25 to +15 degrees), Gaussians at 2-60 m around the sensor within that band
with angular footprints chosen like the camera's (N * pi * (2 s)^2 = coverage x the band's
solid angle in degrees^2), 2 feature channels; the backward is that of a weighted sum of
range, median range, alpha and features. Rows record the grid as height (beams) x width
(azimuths).

A per-rasterizer time cap skips cases whose estimated run time (from the largest measured
smaller case, scaled by the larger of the Gaussian-count and pixel-count ratios) exceeds it; the child also stops early if its
first iteration shows the cap would be exceeded.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import tyro

from omnire.bench.machine import machine_info
from omnire.errors import ConfigError
from omnire.bench.memory import process_status_kib


@dataclasses.dataclass
class BenchArgs:
    """Benchmark the installed rasterizers on random scenes."""

    gaussians: tuple[int, ...] = (10_000, 50_000, 200_000)
    """Gaussian counts."""
    resolutions: tuple[str, ...] = ("160x240", "320x480", "640x960")
    """Image sizes as HEIGHTxWIDTH."""
    repeats: int = 5
    """Timed iterations per case (medians are reported)."""
    warmup: int = 1
    """Untimed iterations per case."""
    output: Optional[Path] = None
    """Where the JSON results go (written atomically); default outputs/bench/raster.json,
    with --lidar outputs/bench/raster_lidar.json."""
    rasterizers: tuple[str, ...] = ()
    """Rasterizer names; empty = every installed rasterizer available on the device."""
    device: str = "cpu"
    """Device to benchmark on."""
    threads: int = 0
    """torch / rasterizer threads (0 = torch.get_num_threads())."""
    coverage: float = 8.0
    """Scene density: average number of 2-sigma ellipses covering a pixel."""
    time_cap: float = 150.0
    """Seconds allowed per (rasterizer, case); longer estimated cases are skipped."""
    seed: int = 0
    """Scene seed."""
    lidar: bool = False
    """Time rasterize_lidar on beam grids (--lidar-rays) instead of camera images."""
    lidar_rays: tuple[str, ...] = ("64x1800",)
    """With --lidar: beam grids as BEAMSxAZIMUTHS."""
    reference: str = ""
    """Rasterizer the others' speed-ups are measured against (default: the benchmarked one of
    lowest priority, the reference implementation)."""


def parse_resolution(text: str, option: str = "--resolutions") -> tuple[int, int]:
    """``"HxW"`` -> (H, W), both positive; a ConfigError naming ``option`` otherwise."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() and int(p) > 0 for p in parts):
        raise ConfigError(f"{option} {text!r}: expected two positive integers as HEIGHTxWIDTH (beams x azimuths "
                          "with --lidar-rays), e.g. 160x240")
    return int(parts[0]), int(parts[1])


def make_scene(n: int, height: int, width: int, coverage: float = 8.0, seed: int = 0, device: str = "cpu"):
    """Random scene in front of an identity camera. Returns dict of float32 tensors
    means (N,3), quats (N,4), scales (N,3), opacities (N,), colors (N,3), viewmat (4,4), K (3,3)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    f = 0.5 * width / math.tan(math.radians(60.0) / 2)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    z = torch.empty(n).uniform_(2.0, 40.0, generator=g)
    # up to 10% margin outside the image so border tiles see partial Gaussians
    u = torch.empty(n).uniform_(-0.1 * width, 1.1 * width, generator=g)
    v = torch.empty(n).uniform_(-0.1 * height, 1.1 * height, generator=g)
    means = torch.stack([(u - width / 2) * z / f, (v - height / 2) * z / f, z], -1)
    s_px = math.sqrt(coverage * height * width * 1.44 / (n * math.pi * 4.0))  # 1.44: margin area
    scales = (s_px * z / f)[:, None] * torch.exp(0.4 * torch.randn(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.empty(n).uniform_(0.05, 0.95, generator=g)
    colors = torch.rand(n, 3, generator=g)
    out = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=viewmat, K=K)
    return {k: t.to(device) for k, t in out.items()}


LIDAR_ELEVATIONS = (-25.0, 15.0)
"""Elevation band (degrees) of the --lidar beam grids and scenes."""


def make_lidar_scene(n: int, beams: int, azimuths: int, coverage: float = 8.0, seed: int = 0):
    """Random Gaussians around a sensor at the origin and its beam grid (module docstring).
    Returns dict of float32 tensors means (N,3), quats (N,4), scales (N,3), opacities (N,),
    colors (N,2), and the LidarRays."""
    import torch

    from omnire.rasterization import LidarRays

    g = torch.Generator().manual_seed(seed)
    lo, hi = LIDAR_ELEVATIONS
    rng = torch.empty(n).uniform_(2.0, 60.0, generator=g)
    az = torch.deg2rad(torch.empty(n).uniform_(0.0, 360.0, generator=g))
    el = torch.deg2rad(torch.empty(n).uniform_(lo - 1.0, hi + 1.0, generator=g))
    means = rng[:, None] * torch.stack([torch.cos(el) * torch.cos(az), torch.cos(el) * torch.sin(az), torch.sin(el)],
                                       -1)
    s_deg = math.sqrt(coverage * 360.0 * (hi - lo) / (n * math.pi * 4.0))
    scales = (rng * math.radians(s_deg))[:, None] * torch.exp(0.4 * torch.randn(n, 3, generator=g))
    grid_az = (torch.arange(azimuths, dtype=torch.float64) * (360.0 / azimuths)).repeat(beams)
    grid_el = torch.linspace(lo, hi, beams, dtype=torch.float64).repeat_interleave(azimuths)
    rays = LidarRays(torch.eye(4), grid_az.float(), grid_el.float(), 0.3, 200.0)
    return dict(means=means, quats=torch.randn(n, 4, generator=g), scales=scales,
                opacities=torch.empty(n).uniform_(0.05, 0.95, generator=g), colors=torch.rand(n, 2, generator=g),
                rays=rays)


def _child(spec_json: str) -> None:
    """Run one case; print one JSON line with the result."""
    import torch

    from omnire.camera import Camera
    from omnire.plugins import load_plugins
    from omnire.rasterization import Splats, select_rasterizer

    spec = json.loads(spec_json)
    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    plugins = load_plugins()
    rast = select_rasterizer(plugins, spec["rasterizer"], spec["device"])
    H, W = spec["height"], spec["width"]
    gen = torch.Generator().manual_seed(1)
    if spec.get("lidar"):
        from omnire.rasterization import LidarRays

        scene = make_lidar_scene(spec["n"], H, W, spec["coverage"], spec["seed"])
        rays = scene.pop("rays")
        rays = LidarRays(*(t.to(spec["device"]) for t in (rays.sensor_to_world, rays.azimuth_deg, rays.elevation_deg)),
                         rays.min_range, rays.max_range)
        scene = {k: t.to(spec["device"]) for k, t in scene.items()}
        weights = [(scale * torch.rand(len(rays), *shape, generator=gen)).to(spec["device"])
                   for scale, shape in ((0.01, ()), (0.01, ()), (1.0, ()), (1.0, (2,)))]
    else:
        scene = make_scene(spec["n"], H, W, spec["coverage"], spec["seed"], spec["device"])
        w_rgb = torch.rand(H, W, 3, generator=gen).to(spec["device"])
        w_depth = (0.01 * torch.rand(H, W, 1, generator=gen)).to(spec["device"])
        w_alpha = torch.rand(H, W, 1, generator=gen).to(spec["device"])
    sync = torch.cuda.synchronize if spec["device"].startswith("cuda") else (lambda: None)
    if spec["device"].startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    base = process_status_kib("VmRSS")
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        hwm_reset = True
    except OSError:
        hwm_reset = False
    fwd, bwd = [], []
    note = ""
    total = spec["warmup"] + spec["repeats"]
    t_start = time.perf_counter()
    for it in range(total):
        leaves = {k: v.detach().clone().requires_grad_(k not in ("viewmat", "K")) for k, v in scene.items()}
        splats = Splats(*(leaves[k] for k in ("means", "quats", "scales", "opacities", "colors")))
        sync()
        if spec.get("lidar"):
            t0 = time.perf_counter()
            out = rast.rasterize_lidar(splats, rays)
            sync()
            t1 = time.perf_counter()
            loss = sum((o * w).sum() for o, w in zip((out.range, out.median_range, out.alpha, out.features), weights))
        else:
            camera = Camera.from_world_to_cam(leaves["viewmat"], leaves["K"], W, H)
            t0 = time.perf_counter()
            out = rast.rasterize(splats, camera)
            sync()
            t1 = time.perf_counter()
            loss = (out.rgb * w_rgb).sum() + (out.depth * w_depth).sum() + (out.alpha * w_alpha).sum()
        loss.backward()
        sync()
        t2 = time.perf_counter()
        if it >= spec["warmup"]:
            fwd.append((t1 - t0) * 1e3)
            bwd.append((t2 - t1) * 1e3)
        del out, loss, leaves, splats
        elapsed = time.perf_counter() - t_start
        if it + 1 < total and elapsed / (it + 1) * total > spec["time_cap"]:
            if not fwd:  # keep the (warm-up) sample rather than nothing
                fwd.append((t1 - t0) * 1e3)
                bwd.append((t2 - t1) * 1e3)
            note = f"stopped after {it + 1} of {total} iterations (time cap {spec['time_cap']:.0f} s)"
            break
    if spec["device"].startswith("cuda"):
        peak_mb = torch.cuda.max_memory_allocated() / 2**20
        mem_note = "CUDA max_memory_allocated"
    else:
        peak_mb = max(0, process_status_kib("VmHWM") - base) / 1024
        mem_note = "" if hwm_reset else "upper bound (peak RSS counter not resettable)"

    def median(xs):
        xs = sorted(xs)
        return xs[len(xs) // 2] if len(xs) % 2 else 0.5 * (xs[len(xs) // 2 - 1] + xs[len(xs) // 2])

    print(json.dumps(dict(forward_ms=median(fwd), backward_ms=median(bwd), peak_extra_mb=peak_mb,
                          samples=len(fwd), note="; ".join(x for x in (note, mem_note) if x))))


def _run_case(spec: dict, timeout: float) -> dict:
    cmd = [sys.executable, "-c", "import sys; from omnire.bench.raster import _child; _child(sys.argv[1])",
           json.dumps(spec)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return dict(skipped=True, note=f"timed out after {timeout:.0f} s")
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        err = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return dict(skipped=True, note=f"failed (exit {proc.returncode}): {err[:200]}")
    return json.loads(lines[-1])


def write_json_atomic(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(data, fh, indent=2)
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def main(argv: list[str], plugins) -> int:
    import torch
    from rich.console import Console
    from rich.table import Table

    args = tyro.cli(BenchArgs, args=argv, prog="omnire bench raster")
    console = Console()
    threads = args.threads or torch.get_num_threads()
    device = torch.device(args.device)
    names = list(args.rasterizers) or plugins.rasterizers.names()
    chosen = []
    for name in names:
        if name not in plugins.rasterizers:
            console.print(f"[yellow]skip[/] {name}: not installed (installed: {', '.join(plugins.rasterizers.names())})")
            continue
        spec = plugins.rasterizers.get(name)
        ok, reason = spec.available(device)
        if ok and args.lidar and "lidar" not in spec.capabilities:
            console.print(f"[yellow]skip[/] {name}: no lidar capability")
        elif ok:
            chosen.append(name)
        else:
            console.print(f"[yellow]skip[/] {name}: unavailable on {device}: {reason}")
    if not chosen:
        console.print("[red]no rasterizer to benchmark[/]")
        return 1
    grids = args.lidar_rays if args.lidar else args.resolutions
    option = "--lidar-rays" if args.lidar else "--resolutions"
    cases = sorted(((n, *parse_resolution(r, option)) for n in args.gaussians for r in grids),
                   key=lambda c: (c[0] * c[1] * c[2], c[0]))
    results = []
    for name in chosen:
        measured: list[tuple[int, int, float]] = []  # (N, pixels, seconds per iteration)
        for n, h, w in cases:
            row = dict(rasterizer=name, gaussians=n, height=h, width=w, threads=threads)
            est = None
            smaller = [m for m in measured if m[0] <= n and m[1] <= h * w]
            if smaller:
                mn, mp, ms = max(smaller, key=lambda m: m[0] * m[1])
                # rasterizing cost ~ pixels x coverage (fixed), projection/sorting ~ N
                est = ms * max(n / mn, h * w / mp) * (args.warmup + args.repeats)
            if est is not None and est > args.time_cap:
                row.update(skipped=True, note=f"estimated {est:.0f} s > time cap {args.time_cap:.0f} s")
            else:
                spec = dict(rasterizer=name, n=n, height=h, width=w, threads=threads, device=args.device,
                            warmup=args.warmup, repeats=args.repeats, coverage=args.coverage, seed=args.seed,
                            time_cap=args.time_cap, lidar=args.lidar)
                row.update(_run_case(spec, timeout=max(300.0, 4 * args.time_cap)))
                if not row.get("skipped"):
                    measured.append((n, h * w, (row["forward_ms"] + row["backward_ms"]) / 1e3))
            results.append(row)
            status = "skipped: " + row["note"] if row.get("skipped") else \
                f"fwd {row['forward_ms']:.1f} ms, bwd {row['backward_ms']:.1f} ms, +{row['peak_extra_mb']:.0f} MB"
            console.print(f"  {name:>8} {n:>7} @ {h}x{w}: {status}")

    # speed-up of each rasterizer against the reference in the same run
    benchmarked = sorted({r["rasterizer"] for r in results}, key=lambda n: plugins.rasterizers.get(n).priority)
    reference = args.reference or (benchmarked[0] if benchmarked else "")
    ref = {(r["gaussians"], r["height"], r["width"]): r for r in results if r["rasterizer"] == reference
           and not r.get("skipped")}
    for r in results:
        key = (r["gaussians"], r["height"], r["width"])
        if not r.get("skipped") and key in ref and r["rasterizer"] != reference:
            rr = ref[key]
            r["speedup_vs_reference"] = (rr["forward_ms"] + rr["backward_ms"]) / (r["forward_ms"] + r["backward_ms"])

    what = "rasterize_lidar" if args.lidar else "rasterizers"
    table = Table(title=f"{what} on {device}, {threads} threads (medians of {args.repeats})")
    for col in ("rasterizer", "Gaussians", "beams x azimuths" if args.lidar else "HxW", "forward ms", "backward ms",
                "fwd+bwd ms", "peak extra MB",
                f"vs {reference}", "note"):
        table.add_column(col, justify="left" if col in ("rasterizer", "note", "HxW") else "right")
    for r in results:
        if r.get("skipped"):
            table.add_row(r["rasterizer"], str(r["gaussians"]), f"{r['height']}x{r['width']}", "-", "-", "-", "-", "-",
                          r["note"])
            continue
        sp = r.get("speedup_vs_reference")
        table.add_row(r["rasterizer"], str(r["gaussians"]), f"{r['height']}x{r['width']}", f"{r['forward_ms']:.1f}",
                      f"{r['backward_ms']:.1f}", f"{r['forward_ms'] + r['backward_ms']:.1f}",
                      f"{r['peak_extra_mb']:.0f}", f"{sp:.1f}x" if sp else "-", r.get("note", ""))
    console.print(table)
    payload = dict(machine=machine_info(threads), device=str(device), threads=threads, repeats=args.repeats,
                   lidar=args.lidar,
                   warmup=args.warmup, reference=reference,
                   coverage=args.coverage, seed=args.seed, torch=torch.__version__,
                   time=time.strftime("%Y-%m-%dT%H:%M:%S"), results=results)
    output = args.output or Path("outputs/bench/raster_lidar.json" if args.lidar else "outputs/bench/raster.json")
    write_json_atomic(output, payload)
    console.print(f"wrote {output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
