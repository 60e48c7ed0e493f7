"""Evaluation protocol: reconstruction (training frames) and novel view synthesis
(held-out frames), PSNR / SSIM on full images, LiDAR depth RMSE, and the trivial baseline
"copy the nearest training frame of the same camera" next to every NVS number (a method
that does not beat it has not synthesised a view; DESIGN.md section 6)."""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from omnire.data.scene import View
from omnire.metrics import depth_errors, psnr, ssim


def _mean(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


def nearest_train_frame(frame: int, train_frames: np.ndarray) -> int:
    """The training frame closest in index (the earlier one on ties)."""
    d = np.abs(train_frames - frame)
    return int(train_frames[np.flatnonzero(d == d.min())[0]])


@torch.no_grad()
def evaluate_views(trainer, views: list[View], with_copy_baseline: bool) -> dict:
    psnrs, ssims, rmses, copy_psnrs, copy_ssims = [], [], [], [], []
    t0 = time.perf_counter()
    for view in views:
        result = trainer.model.render(view, trainer.sh_degree())
        target = trainer.target(view)
        psnrs.append(psnr(result.rgb, target))
        ssims.append(ssim(result.rgb, target))
        lidar = trainer.lidar.get(view)
        if lidar is not None:
            rmses.append(depth_errors(result.depth, lidar[0], lidar[1])[0])
        if with_copy_baseline:
            near = nearest_train_frame(view.frame, trainer.scene.train_frames)
            other = trainer.target(View(view.camera, near))
            copy_psnrs.append(psnr(other, target))
            copy_ssims.append(ssim(other, target))
    seconds = time.perf_counter() - t0
    out = {
        "views": len(views),
        "psnr": _mean(psnrs),
        "ssim": _mean(ssims),
        "depth_rmse": _mean(rmses),
        "render_fps": len(views) / seconds if seconds > 0 else float("nan"),
    }
    if with_copy_baseline:
        out["copy_nearest_psnr"] = _mean(copy_psnrs)
        out["copy_nearest_ssim"] = _mean(copy_ssims)
    return out


def evaluate_model(trainer) -> dict:
    train_views = trainer.train_views
    limit = trainer.config.trainer.eval_train_views
    if limit and len(train_views) > limit:
        idx = np.linspace(0, len(train_views) - 1, limit).round().astype(int)
        train_views = [train_views[i] for i in idx]
    result = {
        "step": trainer.step,
        "num_gaussians": trainer.model.num_gaussians(),
        "reconstruction": evaluate_views(trainer, train_views, with_copy_baseline=False),
    }
    if trainer.test_views:
        result["novel_view"] = evaluate_views(trainer, trainer.test_views, with_copy_baseline=True)
    return result


def format_table(result: dict, title: str = "evaluation") -> "rich.table.Table":
    from rich.table import Table

    table = Table(title=title)
    for col in ["split", "views", "PSNR", "SSIM", "depth RMSE (m)", "copy-nearest PSNR", "copy-nearest SSIM"]:
        table.add_column(col)
    for split, key in [("reconstruction (train)", "reconstruction"), ("novel view (held-out)", "novel_view")]:
        r = result.get(key)
        if not r:
            continue
        table.add_row(split, str(r["views"]), f"{r['psnr']:.2f}", f"{r['ssim']:.3f}", f"{r['depth_rmse']:.2f}",
                      f"{r['copy_nearest_psnr']:.2f}" if "copy_nearest_psnr" in r else "-",
                      f"{r['copy_nearest_ssim']:.3f}" if "copy_nearest_ssim" in r else "-")
    return table
