"""Dynamic masks from projected boxes against per-pixel ray casting; sky heuristic."""
import numpy as np
import torch

from omnire.data.images import ImageCache
from omnire.data.scene import View
from omnire.masks import DynamicMasks, SkyMasks, box_polygon, fill_convex

from scene_helpers import LOOK_X


def ray_box_hits(pose, size, c2w, K, W, H):
    """(H,W) bool: does the ray through each pixel centre hit the box (slab test)?"""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    # into box coordinates
    d_l = d @ pose[:3, :3]
    o_l = (o - pose[:3, 3]) @ pose[:3, :3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-size / 2 - o_l) / d_l
        t2 = (size / 2 - o_l) / d_l
    tmin = np.nanmax(np.minimum(t1, t2), -1)
    tmax = np.nanmin(np.maximum(t1, t2), -1)
    return (tmax >= np.maximum(tmin, 0.1))


def test_box_mask_matches_ray_casting():
    K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = LOOK_X
    for yaw, x, y in [(0.3, 8.0, 1.0), (1.2, 5.0, -2.0), (0.0, 1.5, 0.0)]:  # last one crosses the near plane
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        pose[:3, 3] = [x, y, -0.5]
        size = np.array([4.0, 1.8, 1.5])
        poly = box_polygon(pose, size, np.linalg.inv(c2w), K)
        mask = fill_convex(poly, 80, 60)
        truth = ray_box_hits(pose, size, c2w, K, 80, 60)
        disagree = (mask != truth).mean()
        assert disagree < 0.02, disagree  # only boundary pixels may differ
        assert mask.sum() > 50


def test_dynamic_masks_and_sky(tiny_scene):
    dm = DynamicMasks(tiny_scene, ImageCache(), torch.device("cpu"))
    veh = dm.get(View(0, 0), "vehicle")
    assert veh.shape == (32, 48, 1) and veh.sum() > 0
    assert dm.get(View(0, 0), "human").sum() == 0
    sky = SkyMasks(tiny_scene, ImageCache(), torch.device("cpu")).get(View(0, 1))
    # the tiny scene's wall stops at z = 4 m: the image rows looking above it are sky
    assert sky[0].mean() > 0.9 and sky[-1].sum() == 0
