"""A reconstruction's LiDAR scored on held-out sweeps, beside the two baselines (issue 39,
docs/lidar.md "Evaluation on held-out sweeps"): the same every-10th frames as the cameras,
each held-out sweep's rays on its beam grid (``recorded_sweep(..., grid_only=True)``)
rendered in the run's time sectors and scored by :func:`~omnire.lidar_metrics.lidar_metrics`.
``omnire eval``, the trainer's periodic evaluation and ``omnire bench train`` / ``bench
lidar`` carry the figures.
"""
from __future__ import annotations

import math
import time
from typing import Callable, Optional, Sequence

import torch

from omnire.data.scene import SceneData
from omnire.lidar_baselines import baseline_metrics
from omnire.lidar_metrics import Box, RenderedSweep, boxes_at, lidar_metrics, mean_metrics
from omnire.lidarmodel import LidarRender
from omnire.lidarsweep import SensorPath, SweepRays, aimed_from_sectors, recorded_sweep, sensor_path

LIDAR_TABLE_COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("median_abs_range_error", "median \\|range err\\| (m)", 4),
    ("mean_abs_range_error", "mean \\|range err\\| (m)", 3),
    ("mean_relative_range_error", "mean rel. range err", 4),
    ("range_coverage", "range coverage", 3),
    ("intensity_rmse", "intensity RMSE", 4),
    ("drop_accuracy", "ray-drop acc.", 3),
    ("drop_f1", "ray-drop F1", 3),
    ("chamfer", "Chamfer (m)", 3),
    ("vehicle_median_abs_range_error", "vehicle median err (m)", 4),
    ("vehicle_mean_abs_range_error", "vehicle mean err (m)", 3),
    ("human_median_abs_range_error", "human median err (m)", 4),
    ("human_mean_abs_range_error", "human mean err (m)", 3),
)
"""(figure key, column title, decimals) of every LiDAR table, in order."""

BASELINES: tuple[tuple[str, str], ...] = (("nearest_sweep", "nearest training sweep, moved"),
                                          ("mesh", "mesh of the 4 nearest training sweeps"))
"""(key in :func:`lidar_baselines`' answer, row title) of the two baselines."""


def lidar_test_frames(scene: SceneData) -> list[int]:
    """The held-out frames that have a sweep (empty without LiDAR)."""
    if scene.lidar is None:
        return []
    have = set(scene.lidar.available_frames())
    return [int(f) for f in scene.test_frames if int(f) in have]


def rendered_sweep(render: LidarRender) -> RenderedSweep:
    """A rendered sweep's per-ray answer as plain arrays: the median range (where the ray's
    transmittance falls to 0.5: the first surface it meets, as a LiDAR return is; the
    expected range blends the surfaces on both sides of a depth edge into points between
    them), the intensity and the ray-drop probability. On the PandaSet demo cut's held-out
    sweeps (docs/lidar.md) the median range scores better than the expected one (median
    range error 9.3 against 14.4 cm, Chamfer 0.41 against 0.55 m, vehicle boxes 12 against
    26 cm at step 929)."""
    drop = render.ray_drop.detach().cpu().double().clamp(0.0, 1.0).numpy()
    return RenderedSweep(render.median_range.detach().cpu().double().numpy(),
                         render.intensity.detach().cpu().double().numpy(), drop)


def score_sweep(render_sweep: Callable[[SweepRays, SensorPath, int], LidarRender], rays: SweepRays,
                path: SensorPath, sectors: int, boxes: Sequence[Box] = ()) -> dict:
    """:func:`~omnire.lidar_metrics.lidar_metrics` of the recorded sweep ``rays`` rendered by
    ``render_sweep(rays, path, sectors)`` (``Reconstruction.render_sweep``'s signature).

    The rays are first re-aimed from the poses their time sectors are cast from
    (:func:`~omnire.lidarsweep.aimed_from_sectors`, as training does): a sector's rays leave
    the sensor's pose at its middle time, up to 6 cm from where they were fired with 4
    sectors at 5 m/s, so the recorded ranges, measured from the firing poses, would
    otherwise differ from a perfect render's by that much along the direction of travel.
    The re-aimed returns are the recorded points (the same points for the Chamfer distance
    and the boxes as the baselines score against)."""
    aimed = aimed_from_sectors(rays, path, sectors)
    return lidar_metrics(rendered_sweep(render_sweep(aimed, path, sectors)), aimed, boxes)


@torch.no_grad()
def evaluate_lidar(recon, frames: Optional[Sequence[int]] = None, sectors: Optional[int] = None) -> Optional[dict]:
    """The mean :func:`~omnire.lidar_metrics.lidar_metrics` of ``recon``'s rendered sweeps
    over ``frames`` (default: the held-out frames with LiDAR), each rendered in ``sectors``
    time sectors (default: the method's ``lidar.sectors``) with the scene's boxes at the
    frame (:func:`score_sweep`); plus ``sweeps`` (how many) and ``seconds`` (rendering and
    scoring). None when the run learned no LiDAR or no frame has a sweep."""
    scene = recon.scene
    frames = lidar_test_frames(scene) if frames is None else [int(f) for f in frames]
    if not recon.renders_lidar or not frames:
        return None
    sectors = recon.method.lidar.sectors if sectors is None else sectors
    path = sensor_path(scene)
    scores = []
    seconds = 0.0
    for frame in frames:
        rays = recorded_sweep(scene, frame, grid_only=True)
        t0 = time.perf_counter()
        scores.append(score_sweep(recon.render_sweep, rays, path, sectors, boxes_at(scene, frame)))
        seconds += time.perf_counter() - t0
    out = mean_metrics(scores)
    out["sweeps"] = len(frames)
    out["seconds"] = seconds
    return out


def lidar_baselines(scene: SceneData) -> Optional[dict[str, dict]]:
    """Both baselines (:func:`~omnire.lidar_baselines.baseline_metrics`) on the held-out
    sweeps, built from the training sweeps; None when no held-out or training frame has a
    sweep or the sensor has no beam model (the mesh needs its grid, the nearest sweep its
    angular tolerance)."""
    if not lidar_test_frames(scene) or scene.lidar.beam_model is None:
        return None
    have = set(scene.lidar.available_frames())
    if not any(int(f) in have for f in scene.train_frames):
        return None
    return baseline_metrics(scene, scene.test_frames, scene.train_frames)


def lidar_rows(evaluation: dict) -> list[tuple[str, dict]]:
    """(row title, figures) of an evaluation's LiDAR: the rendered sweeps, then each
    baseline it carries (empty without LiDAR figures)."""
    if not evaluation.get("lidar"):
        return []
    rows = [("rendered", evaluation["lidar"])]
    baselines = evaluation.get("lidar_baselines") or {}
    rows += [(title, baselines[key]) for key, title in BASELINES if key in baselines]
    return rows


def format_value(value, decimals: int) -> str:
    """A figure as table text: ``-`` for None or NaN."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{decimals}f}"


def format_lidar_table(evaluation: dict, title: str = "LiDAR on held-out sweeps"):
    """A rich table of :func:`lidar_rows` (None without LiDAR figures)."""
    from rich.table import Table

    rows = lidar_rows(evaluation)
    if not rows:
        return None
    table = Table(title=f"{title} (sweeps: {evaluation['lidar'].get('sweeps', '?')})")
    table.add_column("renderer", no_wrap=True)
    for _, name, _ in LIDAR_TABLE_COLUMNS:
        table.add_column(name.replace("\\|", "|"))
    for name, figures in rows:
        table.add_row(name, *[format_value(figures.get(key), d) for key, _, d in LIDAR_TABLE_COLUMNS])
    return table



def lidar_markdown_table(results: list[dict]) -> list[str]:
    """Markdown lines of a benchmark's LiDAR figures: one row per method result (``omnire
    bench train``'s form, its ``final`` figures flattened as :func:`omnire.rundir.flatten_eval`
    does) that carries ``lidar.*`` figures, then one row per baseline (from the first such
    result: the baselines depend on the scene and split alone). Empty when no result has
    LiDAR figures."""
    rows = [(r["method"], r["final"]) for r in results if "lidar.sweeps" in r.get("final", {})]
    if not rows:
        return []
    lines = ["| renderer | " + " | ".join(title for _, title, _ in LIDAR_TABLE_COLUMNS) + " | sweeps |",
             "|" + "---|" * (len(LIDAR_TABLE_COLUMNS) + 2)]
    for name, f in rows:
        lines.append(f"| {name} | " + " | ".join(format_value(f.get(f"lidar.{key}"), d)
                                                 for key, _, d in LIDAR_TABLE_COLUMNS) + f" | {f['lidar.sweeps']} |")
    first = rows[0][1]
    for key, title in BASELINES:
        if f"lidar_baselines.{key}.rays" in first:
            lines.append(f"| {title} | " + " | ".join(format_value(first.get(f"lidar_baselines.{key}.{k}"), d)
                                                      for k, _, d in LIDAR_TABLE_COLUMNS) + f" | {first['lidar.sweeps']} |")
    return lines
