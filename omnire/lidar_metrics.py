"""Scores of a rendered LiDAR sweep against the recorded one, ray by ray (docs/lidar.md,
"Evaluation"). The renderer answers every ray of the recorded sweep
(:class:`~omnire.lidarsweep.SweepRays`) with a range, an intensity and a ray-drop
probability (:class:`RenderedSweep`); plain arrays, so any renderer (the Gaussians, the
baselines of :mod:`omnire.lidar_baselines`) is scored the same way.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from omnire.data.scene import SceneData, SceneDataError
from omnire.lidarsweep import SweepRays
from omnire.metrics import chamfer_distance
from omnire.pointcloud import points_in_box


@dataclasses.dataclass
class RenderedSweep:
    """A renderer's answer for R rays.

    Attributes:
        range: (R,) metres along the ray; NaN where the renderer gives no range (a
            baseline's ray that hit nothing).
        intensity: (R,) predicted intensity (NaN where none).
        drop_probability: (R,) in [0, 1], the probability that the ray returns nothing.
    """

    range: np.ndarray
    intensity: np.ndarray
    drop_probability: np.ndarray

    def __post_init__(self) -> None:
        R = len(self.range)
        for name in ("range", "intensity", "drop_probability"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (R,):
                raise SceneDataError(f"rendered sweep: {name} has shape {value.shape}, expected ({R},) (one per ray)")
            setattr(self, name, value)
        p = self.drop_probability
        if not (np.isfinite(p).all() and p.min(initial=0.0) >= 0.0 and p.max(initial=0.0) <= 1.0):
            raise SceneDataError("rendered sweep: drop_probability must hold finite values in [0, 1]")


@dataclasses.dataclass
class Box:
    """An actor's box at the sweep's time: ``box_to_world`` (4, 4), ``size`` (3,) length,
    width, height in metres, and its category (omnire.data.scene.CATEGORIES)."""

    box_to_world: np.ndarray
    size: np.ndarray
    category: str


def boxes_at(scene: SceneData, frame: int) -> list[Box]:
    """The boxes of the actors present at ``frame`` (their poses at the frame's timestamp)."""
    return [Box(t.poses[frame], np.asarray(t.size, dtype=np.float64), t.category)
            for t in scene.tracks if t.present[frame]]


BOX_CATEGORIES = ("vehicle", "human")
"""Categories whose boxes get their own range errors."""


def lidar_metrics(rendered: RenderedSweep, recorded: SweepRays, boxes: Sequence[Box] = (),
                  drop_threshold: float = 0.5) -> dict:
    """Every figure of one sweep (keys below; NaN where a figure has nothing to count).

    A ray is predicted dropped when its probability exceeds ``drop_threshold``; the renderer
    answers a ray when it predicts a return and gives a range (a baseline answers exactly
    the rays it gives a range, a Gaussian render every ray it predicts to return), and every
    figure but ray drop is over the rays it answers, so all renderers are scored alike.
    Range figures are over the recorded returns it answers (``range_coverage`` = their
    share of the recorded returns): ``median_abs_range_error`` and ``mean_abs_range_error``
    (metres, |rendered - recorded|), ``mean_relative_range_error`` (|rendered - recorded| /
    recorded). ``intensity_rmse`` is over those with a rendered and a recorded intensity.
    Ray drop (only when the recorded rays are the full beam grid): ``drop_accuracy`` over
    all rays, ``drop_f1`` the F1 score of the "dropped" class. ``chamfer`` (metres): the
    mean distance from each rendered point (the answered rays) to the nearest recorded
    return plus the mean distance from each recorded return to the nearest rendered point.
    For each category of :data:`BOX_CATEGORIES`, ``<category>_median_abs_range_error``,
    ``..._mean_abs_range_error`` over the answered recorded returns inside one of its
    ``boxes`` and ``<category>_returns``, the recorded returns inside.
    """
    R = len(recorded)
    if len(rendered.range) != R:
        raise SceneDataError(f"rendered sweep has {len(rendered.range)} rays, the recorded sweep {R}")
    ret = recorded.returned
    predicted_drop = rendered.drop_probability > drop_threshold
    answered = ~predicted_drop & np.isfinite(rendered.range)  # (R,) the rays rendered as a point
    has_range = ret & answered
    err = np.abs(rendered.range - recorded.range)  # (R,), NaN off has_range
    out: dict = {"rays": R, "returns": int(ret.sum())}
    out["range_coverage"] = float(has_range.sum() / ret.sum()) if ret.any() else float("nan")
    out.update(_range_errors(err, has_range, ""))
    out["mean_relative_range_error"] = (float(np.mean(err[has_range] / recorded.range[has_range]))
                                        if has_range.any() else float("nan"))
    both = has_range & np.isfinite(rendered.intensity) & np.isfinite(recorded.intensity)
    out["intensity_rmse"] = (float(np.sqrt(np.mean((rendered.intensity[both] - recorded.intensity[both]) ** 2)))
                             if both.any() else float("nan"))
    if recorded.drops_known and R:
        dropped = ~ret
        out["drop_accuracy"] = float(np.mean(predicted_drop == dropped))
        tp = int((predicted_drop & dropped).sum())
        wrong = int((predicted_drop != dropped).sum())
        out["drop_f1"] = 2 * tp / (2 * tp + wrong) if 2 * tp + wrong else float("nan")
    else:
        out["drop_accuracy"] = out["drop_f1"] = float("nan")
    pred_points = recorded.origins[answered] + recorded.directions[answered] * rendered.range[answered, None]
    out["chamfer"] = chamfer_distance(pred_points, recorded.points())
    points = recorded.origins + recorded.directions * np.nan_to_num(recorded.range)[:, None]
    for category in BOX_CATEGORIES:
        inside = np.zeros(R, dtype=bool)
        for box in boxes:
            if box.category == category:
                inside[ret] |= points_in_box(points[ret], box.box_to_world, box.size)
        out[f"{category}_returns"] = int(inside.sum())
        out.update(_range_errors(err, has_range & inside, f"{category}_"))
    return out


def _range_errors(err: np.ndarray, keep: np.ndarray, prefix: str) -> dict:
    if not keep.any():
        return {f"{prefix}median_abs_range_error": float("nan"), f"{prefix}mean_abs_range_error": float("nan")}
    return {f"{prefix}median_abs_range_error": float(np.median(err[keep])),
            f"{prefix}mean_abs_range_error": float(np.mean(err[keep]))}


def mean_metrics(per_sweep: Sequence[dict]) -> dict:
    """The mean of each figure over sweeps (NaNs left out; counts summed)."""
    out: dict = {}
    for key in per_sweep[0] if per_sweep else ():
        values = np.array([m[key] for m in per_sweep], dtype=np.float64)
        if key in ("rays", "returns") or key.endswith("_returns"):
            out[key] = int(values.sum())
        else:
            finite = values[np.isfinite(values)]
            out[key] = float(finite.mean()) if len(finite) else float("nan")
    return out
