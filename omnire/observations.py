"""What was recorded for each view of a scene, as losses and metrics consume it: the image,
the LiDAR depth at its pixels, dynamic (human / vehicle) masks and sky masks. Everything is
loaded lazily and cached per view, so a scene runtime that only renders reads none of it.
"""
from __future__ import annotations

from typing import Optional

import torch

from omnire.data.images import ImageCache
from omnire.data.scene import SceneData, View
from omnire.lidar import LidarDepthTargets
from omnire.masks import DynamicMasks, SkyMasks


class Observations:
    """The recorded data of ``scene`` per view, on ``device``."""

    def __init__(self, scene: SceneData, device: torch.device, images: Optional[ImageCache] = None) -> None:
        self.scene = scene
        self.device = device
        self.images = images if images is not None else ImageCache()
        self._lidar = LidarDepthTargets(scene, device)
        self._dynamic = DynamicMasks(scene, self.images, device)
        self._sky = SkyMasks(scene, self.images, device)

    def image(self, view: View) -> torch.Tensor:
        """(H, W, 3) float image in [0, 1]."""
        return self.images.camera_image(self.scene.cameras[view.camera], view.frame).to(self.device)

    def lidar(self, view: View) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
        """(flat pixel indices (P,), camera-z depths (P,)) of the frame's LiDAR in the view,
        or None without LiDAR at that frame."""
        return self._lidar.get(view)

    def dynamic_mask(self, view: View, kind: str) -> torch.Tensor:
        """(H, W, 1) {0, 1} mask of ``kind`` in {"human", "vehicle", "all"}."""
        return self._dynamic.get(view, kind)

    def sky_mask(self, view: View) -> Optional[torch.Tensor]:
        """(H, W, 1) {0, 1} sky mask, or None when neither the dataset nor LiDAR gives one."""
        return self._sky.get(view)

    def preload(self, views: list[View], sky: bool = False) -> None:
        """Decode every image and build every mask of ``views`` now (e.g. before timing)."""
        for v in views:
            self.image(v)
            self.lidar(v)
            self.dynamic_mask(v, "all")
            if sky:
                self.sky_mask(v)
