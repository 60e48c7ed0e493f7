"""What a training step with LiDAR renders: a training frame's recorded sweep, a random
subset of its rays, and the loss terms of rendering them (the trainer's ``lidar`` stage,
omnire/trainer.py).

The frame and the rays are drawn from a generator of their own (seeded, saved in
checkpoints), so switching LiDAR on does not change which camera views a run trains on.
Recorded sweeps are read once per frame and kept, with their depth edges.
"""
from __future__ import annotations

import dataclasses
import logging
from typing import TYPE_CHECKING, Optional

import numpy as np
import torch

from omnire.lidarloss import lidar_loss_terms, line_of_sight_probes
from omnire.lidarmodel import LidarConfig
from omnire.lidarsweep import SweepRays, aimed_from_sectors, depth_edges, recorded_sweep, sensor_path

if TYPE_CHECKING:
    from omnire.runtime import Reconstruction

log = logging.getLogger("omnire.lidar")


class LidarTraining:
    """Samples training sweeps of ``recon``'s scene and renders them (see the module docstring).

    Attributes:
        frames: (K,) training frames that have LiDAR.
        sampler: the generator drawing frames and rays.
    """

    def __init__(self, recon: "Reconstruction", seed: int, edge_jump: Optional[float] = None) -> None:
        scene = recon.scene
        self.recon = recon
        self.edge_jump = edge_jump
        self.frames = np.array([int(f) for f in scene.train_frames if scene.lidar.points[int(f)] is not None])
        self.path = sensor_path(scene)
        self.sampler = torch.Generator().manual_seed(seed)
        self._sweeps: dict[int, SweepRays] = {}
        if len(self.frames) == 0:
            log.warning("LiDAR rendering is on but no training frame has LiDAR: no LiDAR loss")
        elif not self.sweep(int(self.frames[0])).drops_known:
            log.info("LiDAR: the scene's sweeps have no beams, so their missing returns are unknown: "
                     "no ray-drop loss (range and intensity only)")

    def sweep(self, frame: int) -> SweepRays:
        """The recorded sweep of ``frame`` (read once)."""
        if frame not in self._sweeps:
            sweep = recorded_sweep(self.recon.scene, frame)
            model, jump = self.recon.scene.lidar.beam_model, self.edge_jump
            if model is not None and sweep.drops_known and jump is not None:
                sweep = dataclasses.replace(sweep, depth_edge=depth_edges(sweep, model, jump))
            self._sweeps[frame] = sweep
        return self._sweeps[frame]

    def sample(self, rays_per_step: int) -> SweepRays:
        """A random training frame's sweep, cut to ``rays_per_step`` random rays (0: all)."""
        frame = int(self.frames[int(torch.randint(len(self.frames), (1,), generator=self.sampler))])
        sweep = self.sweep(frame)
        if 0 < rays_per_step < len(sweep):
            rows = torch.randperm(len(sweep), generator=self.sampler)[:rays_per_step].sort().values.numpy()
            sweep = sweep.select(rows)
        return sweep

    def loss_terms(self, config: LidarConfig, step: int) -> dict[str, torch.Tensor]:
        """The weighted LiDAR loss terms of one sampled sweep rendered at training ``step``."""
        if len(self.frames) == 0:
            return {}
        sweep = aimed_from_sectors(self.sample(config.rays_per_step), self.path, config.sectors)
        probes = line_of_sight_probes(sweep, config, self.sampler)
        render = self.recon.render_sweep(sweep, self.path, config.sectors, step=step,
                                         probe_range=None if probes is None else probes.range)
        return lidar_loss_terms(render, sweep, config, probes)
