"""``omnire bench skip``: measure that the framework skips what a scene does not need.

1. No humans: on the scene with its pedestrian and cyclist tracks removed, ``omnire`` must
   build no SMPL or deformable node and cost the same per step as ``streetgs``.
2. Absent actors: adding many short-lived actors that are absent from the rendered frames
   must not change the cost of a step at those frames.
3. LiDAR rendering: ``--method.lidar.enabled`` on the scene without its LiDAR must cost
   nothing against the same scene with the flag off (no LiDAR features are made, no sweep is
   rendered); on the scene with its LiDAR the cost of the LiDAR steps is measured against the
   flag off (averaged over the steps, one in ``lidar.every`` renders a ray batch), when the
   rasterizer renders LiDAR; with the flag on, the actors only the LiDAR sees get nodes too
   (``omnire.api.observed_in_training``), part of that cost (column ``actors``).

Both run in one process with the same seed, scene, rasterizer and views; per-step times are
medians over ``steps`` training steps after ``warmup`` steps, the configurations of each
comparison stepping in turn (a slow spell of the machine hits all alike). Output: JSON and
a table.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import shlex
import statistics
import time
from pathlib import Path

import numpy as np
import tyro

from omnire.api import UserError, atomic_write_text, visible_in_cameras


@dataclasses.dataclass
class SkipBenchArgs:
    """Measure the cost of what a scene does not need."""

    dataparser: str = "pandaset"
    """Dataparser reading --data."""
    data: Path = Path("data/demo/pandaset_002")
    """Scene directory."""
    scale: float = 0.5
    """Image scale."""
    baseline: str = "streetgs"
    """Method without human nodes to compare omnire with on the scene without humans."""
    steps: int = 30
    """Timed steps per configuration."""
    warmup: int = 5
    """Untimed steps first."""
    extra_actors: tuple[int, ...] = (0, 100, 400)
    """Counts of added short-lived actors (absent from the timed frames)."""
    method_args: str = ""
    """Flags of every compared method, as ``omnire train`` takes them (e.g. ``--method.lidar.rays-per-step
    2000`` or a smaller ``--method.nodes.background.max-lidar-points``)."""
    output: Path = Path("outputs/bench/skip.json")
    """JSON output."""


def _method_configs(plugins, args: SkipBenchArgs, methods: tuple[str, ...]) -> dict:
    """Each method's configuration with ``--method-args`` applied (parsed as ``omnire train`` does)."""
    from omnire.command_api import parse_train_args

    return {m: parse_train_args([m, args.dataparser, "--data", str(args.data), *shlex.split(args.method_args)],
                                plugins).method for m in methods}


def _trainer(plugins, method_configs: dict, method: str, dataparser: str, scene, seed: int = 0, lidar: bool = False):
    from omnire.api import TrainConfig, Trainer, TrainerConfig

    cfg = copy.deepcopy(method_configs[method])
    cfg.lidar.enabled = lidar
    cfg.densify.refine_start = 10**9  # fixed Gaussian count: time the same work
    tc = TrainerConfig(max_steps=10**6, progress=False, seed=seed)
    return Trainer(TrainConfig(method, dataparser, cfg, None, tc), plugins, scene=scene, persist=False)


def _time_steps(trainers: list, views: list[list], warmup: int, steps: int) -> list[float]:
    """Median ms per training step of each trainer on its views. Steps alternate between
    the trainers, so a slow spell of a shared machine hits every configuration alike."""
    rng = np.random.default_rng(0)
    for trainer, vs in zip(trainers, views):
        # decode every image and build every mask first: time rendering and optimisation only
        trainer.observations.preload(vs, sky=trainer.use_sky_masks)
        for _ in range(warmup):
            trainer.train_step(vs[int(rng.integers(len(vs)))])
    times: list[list[float]] = [[] for _ in trainers]
    for _ in range(steps):
        for trainer, vs, ts in zip(trainers, views, times):
            view = vs[int(rng.integers(len(vs)))]
            t0 = time.perf_counter()
            trainer.train_step(view)
            ts.append(time.perf_counter() - t0)
    return [statistics.median(ts) * 1000 for ts in times]


def main(argv: list[str], plugins) -> int:
    """``omnire bench skip``."""
    from rich.console import Console
    from rich.table import Table

    args = tyro.cli(SkipBenchArgs, args=argv, prog="omnire bench skip")
    cfg = plugins.dataparsers.get(args.dataparser).config_factory()
    cfg.data, cfg.scale = args.data, args.scale
    scene = cfg.setup().load()
    out: dict = {"args": {k: str(v) for k, v in dataclasses.asdict(args).items()}}
    method_configs = _method_configs(plugins, args, (args.baseline, "omnire"))

    no_humans = copy.copy(scene)
    no_humans.tracks = [t for t in scene.tracks if t.category not in ("human", "cyclist")]
    no_humans.human_poses = {}
    trainers = [_trainer(plugins, method_configs, method, args.dataparser, no_humans)
                for method in (args.baseline, "omnire")]
    times = _time_steps(trainers, [tr.train_views for tr in trainers], args.warmup, args.steps)
    rows = [{"method": tr.config.method_name, "nodes": list(tr.recon.nodes), "ms_per_step": ms,
             "gaussians": tr.recon.num_gaussians()} for tr, ms in zip(trainers, times)]
    del trainers
    out["no_humans"] = rows
    out["no_humans_overhead"] = rows[1]["ms_per_step"] / rows[0]["ms_per_step"] - 1

    # Absent actors: copies of a real vehicle, present only in the first two frames; steps are
    # timed on frames from the second half, where none of them is present.
    early = np.array([0, 1])
    base = next(t for t in scene.tracks if t.category == "vehicle" and t.present[:2].all()
                and visible_in_cameras(t, scene, early))
    late = set(scene.train_frames[scene.train_frames >= scene.num_frames // 2].tolist())
    trainers, views = [], []
    for k in args.extra_actors:
        s = copy.copy(scene)
        s.tracks = list(scene.tracks)
        for i in range(k):
            t = copy.deepcopy(base)
            t.track_id = f"extra-{i}"
            t.present = np.zeros_like(t.present)
            t.present[:2] = True
            s.tracks.append(t)
        trainers.append(_trainer(plugins, method_configs, args.baseline, args.dataparser, s))
        views.append([v for v in trainers[-1].train_views if v.frame in late])
    times = _time_steps(trainers, views, args.warmup, args.steps)
    absent_rows = [{"extra_actors": k, "rigid_instances": len(tr.recon.assignment.get("rigid", [])),
                    "ms_per_step": ms, "gaussians": tr.recon.num_gaussians()}
                   for k, tr, ms in zip(args.extra_actors, trainers, times)]
    out["absent_actors"] = absent_rows
    del trainers

    # LiDAR rendering off and on, on the scene without its LiDAR (the flag must cost nothing)
    # and with it (the cost of the LiDAR steps, when the rasterizer renders LiDAR)
    no_lidar = copy.copy(scene)
    no_lidar.lidar = None
    configs = [("scene without LiDAR", no_lidar, False), ("scene without LiDAR", no_lidar, True),
               ("scene with LiDAR", scene, False)]
    try:
        probe = _trainer(plugins, method_configs, args.baseline, args.dataparser, scene, lidar=True)
        del probe
        configs.append(("scene with LiDAR", scene, True))
        lidar_note = None
    except UserError as exc:  # the rasterizer renders no LiDAR
        lidar_note = str(exc)
    trainers = [_trainer(plugins, method_configs, args.baseline, args.dataparser, s, lidar=on) for _, s, on in configs]
    times = _time_steps(trainers, [tr.train_views for tr in trainers], args.warmup, args.steps)
    lidar_rows = [{"scene": name, "lidar": on, "parameters": sum(p.numel() for p in tr.model.parameters()),
                   "ms_per_step": ms, "gaussians": tr.recon.num_gaussians(),
                   "actors": sum(len(ids) for ids in tr.recon.assignment.values())}
                  for (name, _, on), tr, ms in zip(configs, trainers, times)]
    out["lidar"] = lidar_rows
    out["lidar_note"] = lidar_note
    args.output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.output, json.dumps(out, indent=2))

    console = Console()
    t1 = Table(title=f"scene without humans: omnire vs {args.baseline}")
    for c in ("method", "nodes", "Gaussians", "ms / step"):
        t1.add_column(c)
    for r in rows:
        t1.add_row(r["method"], ", ".join(r["nodes"]), str(r["gaussians"]), f"{r['ms_per_step']:.1f}")
    console.print(t1)
    console.print(f"omnire overhead: {100 * out['no_humans_overhead']:+.1f}%")
    t2 = Table(title=f"actors absent from the rendered frames ({args.baseline}, frames of the second half)")
    for c in ("extra actors", "rigid instances", "Gaussians", "ms / step"):
        t2.add_column(c)
    for r in absent_rows:
        t2.add_row(str(r["extra_actors"]), str(r["rigid_instances"]), str(r["gaussians"]), f"{r['ms_per_step']:.1f}")
    console.print(t2)
    t3 = Table(title=f"LiDAR rendering ({args.baseline}; on: a ray batch every --method.lidar.every steps, averaged)")
    for c in ("scene", "--method.lidar.enabled", "actors", "Gaussians", "parameters", "ms / step"):
        t3.add_column(c)
    for r in lidar_rows:
        t3.add_row(r["scene"], "on" if r["lidar"] else "off", str(r["actors"]), str(r["gaussians"]), str(r["parameters"]),
                   f"{r['ms_per_step']:.1f}")
    console.print(t3)
    if lidar_note:
        console.print(f"LiDAR on: not measured ({lidar_note})")
    return 0
