"""Evaluation protocol: reconstruction (training frames) and novel view synthesis
(held-out frames), PSNR / SSIM on full images, LiDAR depth RMSE, and the trivial baseline
"copy the nearest training frame of the same camera" next to every NVS number (a method
that does not beat it has not synthesised a view; docs/conventions.md, "The demo log")."""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np
import torch

from omnire.data.scene import View
from omnire.lidar_evaluation import evaluate_lidar
from omnire.metrics import chamfer_distance, depth_errors, psnr, ssim


def _mean(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


def nearest_train_frame(frame: int, train_frames: np.ndarray) -> int:
    """The training frame closest in index (the earlier one on ties)."""
    d = np.abs(train_frames - frame)
    return int(train_frames[np.flatnonzero(d == d.min())[0]])


def backproject(z: torch.Tensor, pixels: torch.Tensor, width: int, K: torch.Tensor, cam_to_world: torch.Tensor) -> torch.Tensor:
    """World points (P,3) at depths ``z`` (P,) (along the camera axis) through the centres of
    flat ``pixels`` (P,) of an image ``width`` wide."""
    W = width
    u = (pixels % W).float() + 0.5
    v = (pixels // W).float() + 0.5
    p = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    return p @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]


@torch.no_grad()
def evaluate_views(recon, observations, views: list[View], with_copy_baseline: bool, max_depth: float = 80.0) -> dict:
    """PSNR/SSIM per region (full image, human mask, vehicle mask), depth RMSE and Chamfer
    distance at LiDAR pixels, render speed; with the copy-nearest-frame baseline.

    ``recon``: the :class:`~omnire.runtime.Reconstruction`; ``observations``: the recorded
    data (:class:`~omnire.observations.Observations`) of its scene."""
    acc: dict[str, list[float]] = {}
    scene = recon.scene

    def add(key: str, value: float) -> None:
        acc.setdefault(key, []).append(value)

    t_render = 0.0
    for view in views:
        t0 = time.perf_counter()
        result = recon.render_view(view)
        t_render += time.perf_counter() - t0
        target = observations.image(view)
        scene_pixels = observations.scene_pixels(view)  # the recording vehicle's pixels are no scene
        masks = {"full": scene_pixels, "human": observations.dynamic_mask(view, "human"),
                 "vehicle": observations.dynamic_mask(view, "vehicle")}
        if scene_pixels is not None:
            masks["human"], masks["vehicle"] = masks["human"] * scene_pixels, masks["vehicle"] * scene_pixels
        near = nearest_train_frame(view.frame, scene.train_frames) if with_copy_baseline else None
        other = observations.image(View(view.camera, near)) if with_copy_baseline else None
        for region, mask in masks.items():
            if mask is not None and not bool((mask > 0.5).any()):
                continue  # region absent from this image: not counted
            add(f"{region}_psnr", psnr(result.rgb, target, mask))
            add(f"{region}_ssim", ssim(result.rgb, target, mask))
            if other is not None:
                add(f"copy_{region}_psnr", psnr(other, target, mask))
                add(f"copy_{region}_ssim", ssim(other, target, mask))
        camera_name = scene.cameras[view.camera].name
        add(f"camera.{camera_name}.psnr", psnr(result.rgb, target, masks["full"]))
        if other is not None:
            add(f"camera.{camera_name}.copy_psnr", psnr(other, target, masks["full"]))
        lidar = observations.lidar(view)
        if lidar is not None and scene_pixels is not None:
            on_scene = scene_pixels.reshape(-1)[lidar[0]] > 0.5
            lidar = (lidar[0][on_scene], lidar[1][on_scene]) if bool(on_scene.any()) else None
        if lidar is not None:
            pix, z = lidar
            add("depth_rmse", depth_errors(result.depth, pix, z, max_depth)[0])
            keep = (z < max_depth) & (result.alpha.reshape(-1)[pix] > 0.5)
            if bool(keep.any()):
                camera = recon.camera(view)
                W = result.depth.shape[1]
                pred = backproject(result.depth.reshape(-1)[pix[keep]], pix[keep], W, camera.K, camera.cam_to_world)
                gt = backproject(z[keep], pix[keep], W, camera.K, camera.cam_to_world)
                add("depth_chamfer", chamfer_distance(pred, gt))
    out = {"views": len(views), "render_fps": len(views) / t_render if t_render > 0 else float("nan")}
    out.update({k: _mean(v) for k, v in sorted(acc.items()) if not k.startswith("camera.")})
    per_camera: dict[str, dict[str, float]] = {}
    for k, v in sorted(acc.items()):
        if k.startswith("camera."):
            _, name, metric = k.split(".", 2)
            per_camera.setdefault(name, {})[metric] = _mean(v)
    out["per_camera"] = per_camera
    out["psnr"], out["ssim"] = out.get("full_psnr", float("nan")), out.get("full_ssim", float("nan"))
    return out


def evaluate(recon, observations, train_views: list[View], test_views: list[View], train_view_limit: int = 0,
             lidar_baselines: Optional[dict] = None) -> dict:
    """Reconstruction metrics on (at most ``train_view_limit``, evenly spaced; 0 = all)
    training views and novel-view metrics on the held-out views; for a run that learned
    LiDAR, ``lidar``: its held-out sweeps' figures (omnire/lidar_evaluation.py), with
    ``lidar_baselines`` (:func:`~omnire.lidar_evaluation.lidar_baselines` of the scene,
    computed once by the caller: they do not change with training) beside them."""
    if train_view_limit and len(train_views) > train_view_limit:
        idx = np.linspace(0, len(train_views) - 1, train_view_limit).round().astype(int)
        train_views = [train_views[i] for i in idx]
    result = {
        "step": recon.step,
        "num_gaussians": recon.num_gaussians(),
        "reconstruction": evaluate_views(recon, observations, train_views, with_copy_baseline=False),
    }
    if test_views:
        result["novel_view"] = evaluate_views(recon, observations, test_views, with_copy_baseline=True)
    lidar = evaluate_lidar(recon)
    if lidar is not None:
        result["lidar"] = lidar
        if lidar_baselines:
            result["lidar_baselines"] = lidar_baselines
    return result


def format_table(result: dict, title: str = "evaluation"):
    """One row per split, columns in the paper's layout: full / human / vehicle PSNR and
    SSIM, depth RMSE and Chamfer; held-out rows add the copy-nearest-frame baseline."""
    from rich.table import Table

    table = Table(title=title)
    cols = ["split", "views", "PSNR", "SSIM", "human PSNR", "human SSIM", "vehicle PSNR", "vehicle SSIM",
            "depth RMSE", "Chamfer"]
    for col in cols:
        table.add_column(col)

    def f(r, k, d=2):
        v = r.get(k, float("nan"))
        return "-" if v != v else f"{v:.{d}f}"

    rows = [("reconstruction", result.get("reconstruction"), ""), ("novel view", result.get("novel_view"), ""),
            ("  copy nearest", result.get("novel_view"), "copy_")]
    for name, r, prefix in rows:
        if not r:
            continue
        table.add_row(name, str(r["views"]), f(r, f"{prefix}full_psnr"), f(r, f"{prefix}full_ssim", 3),
                      f(r, f"{prefix}human_psnr"), f(r, f"{prefix}human_ssim", 3),
                      f(r, f"{prefix}vehicle_psnr"), f(r, f"{prefix}vehicle_ssim", 3),
                      "-" if prefix else f(r, "depth_rmse"), "-" if prefix else f(r, "depth_chamfer", 3))
    return table


def format_camera_table(result: dict, title: str = "novel views per camera"):
    """Held-out PSNR per camera next to the copy-nearest-frame baseline (None without held-out views)."""
    from rich.table import Table

    per_camera = (result.get("novel_view") or {}).get("per_camera") or {}
    if not per_camera:
        return None
    table = Table(title=title)
    for col in ("camera", "PSNR", "copy nearest", "margin"):
        table.add_column(col)
    for name, r in per_camera.items():
        a, b = r.get("psnr", float("nan")), r.get("copy_psnr", float("nan"))
        table.add_row(name, f"{a:.2f}", f"{b:.2f}", f"{a - b:+.2f}")
    return table
