"""What was recorded for each view of a scene, as losses and metrics consume it: the image,
the LiDAR depth at its pixels, dynamic (human / vehicle) masks, sky masks and the mask of the
recording vehicle itself. Everything is loaded lazily and cached, so a scene runtime that
only renders reads none of it.
"""
from __future__ import annotations

from typing import Optional

import logging

import torch

from omnire.data.images import ImageCache
from omnire.data.scene import SceneData, View
from omnire.lidar import LidarDepthTargets
from omnire.masks import DynamicMasks, SkyMasks
from omnire.resolution import downscale_image, downscale_pixel_samples


class Observations:
    """The recorded data of ``scene`` per view, on ``device``."""

    def __init__(self, scene: SceneData, device: torch.device, images: Optional[ImageCache] = None) -> None:
        self.scene = scene
        self.device = device
        self.images = images if images is not None else ImageCache()
        self._lidar = LidarDepthTargets(scene, device)
        self._dynamic = DynamicMasks(scene, self.images, device, lidar=self._lidar)
        self._sky = SkyMasks(scene, self.images, device)
        self._scene_valid: Optional[dict[int, Optional[torch.Tensor]]] = None
        self._downscaled: dict[tuple, object] = {}  # (what, view or camera, factor) -> value

    # Every accessor takes ``factor``: the same data for the view rendered at 1 / factor of
    # its resolution (omnire.resolution: block means of images and masks, LiDAR returns
    # moved to their block), cached beside the full-resolution data.
    def _at(self, key: tuple, factor: int, full, downscale):
        if factor == 1 or full is None:
            return full
        key = key + (factor,)
        if key not in self._downscaled:
            self._downscaled[key] = downscale(full)
        return self._downscaled[key]

    def image(self, view: View, factor: int = 1) -> torch.Tensor:
        """(H, W, 3) float image in [0, 1]."""
        full = self.images.camera_image(self.scene.cameras[view.camera], view.frame).to(self.device)
        return self._at(("image", view), factor, full, lambda t: downscale_image(t, factor))

    def lidar(self, view: View, factor: int = 1) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
        """(flat pixel indices (P,), camera-z depths (P,)) of the frame's LiDAR in the view,
        or None without LiDAR at that frame."""
        cam = self.scene.cameras[view.camera]
        return self._at(("lidar", view), factor, self._lidar.get(view),
                        lambda s: downscale_pixel_samples(s[0], s[1], cam.width, cam.height, factor))

    def dynamic_mask(self, view: View, kind: str, factor: int = 1) -> torch.Tensor:
        """(H, W, 1) {0, 1} mask of ``kind`` in {"human", "vehicle", "all"} (block fractions
        when downscaled)."""
        return self._at(("dynamic", kind, view), factor, self._dynamic.get(view, kind),
                        lambda t: downscale_image(t, factor))

    def sky_mask(self, view: View, factor: int = 1) -> Optional[torch.Tensor]:
        """(H, W, 1) {0, 1} sky mask, or None when neither the dataset nor LiDAR gives one."""
        return self._at(("sky", view), factor, self._sky.get(view), lambda t: downscale_image(t, factor))

    def sky_trusted(self, view: View, factor: int = 1) -> Optional[torch.Tensor]:
        """(H, W, 1): 0 where the sky mask's "sky" is not to be trusted, 1 elsewhere (block
        fractions when downscaled); None when it is trusted everywhere (see SkyMasks)."""
        return self._at(("sky_trusted", view), factor, self._sky.trusted(view), lambda t: downscale_image(t, factor))

    def scene_pixels(self, view: View, factor: int = 1) -> Optional[torch.Tensor]:
        """(H, W, 1) {0, 1}: 0 where the recording vehicle itself is seen (its ego mask), 1
        elsewhere; None when the camera has no ego mask (every pixel is scene)."""
        if self._scene_valid is None:
            self._scene_valid = self._load_ego_masks()
        return self._at(("ego", view.camera), factor, self._scene_valid[view.camera],
                        lambda t: downscale_image(t, factor))

    def _load_ego_masks(self) -> dict[int, Optional[torch.Tensor]]:
        out: dict[int, Optional[torch.Tensor]] = {}
        estimated = {}
        if self.scene.estimate_ego_masks and any(c.ego_mask_path is None for c in self.scene.cameras):
            from omnire.egomask import estimate_scene_ego_masks

            estimated = estimate_scene_ego_masks(self.scene, self.images)
        for i, cam in enumerate(self.scene.cameras):
            if cam.ego_mask_path is not None:
                ego = self.images.get(cam.ego_mask_path, cam.width, cam.height, 1) > 0.5
            elif cam.name in estimated and estimated[cam.name].any():
                ego = torch.from_numpy(estimated[cam.name])[..., None]
            else:
                out[i] = None
                continue
            logging.getLogger("omnire.egomask").info(
                "camera %s: %.1f%% of the image is the recording vehicle (%s)", cam.name, 100 * float(ego.float().mean()),
                cam.ego_mask_path or "estimated")
            out[i] = (~ego).float().to(self.device)
        return out

    def preload(self, views: list[View], sky: bool = False) -> None:
        """Decode every image and build every mask of ``views`` now (e.g. before timing)."""
        for v in views:
            self.image(v)
            self.lidar(v)
            self.dynamic_mask(v, "all")
            if sky:
                self.sky_mask(v)
                self.sky_trusted(v)
