"""The rays of one LiDAR sweep and what came back along them: the recorded sweep of a frame
(returns, plus the missing returns where the scene knows its beams), or every ray of a beam
model from a pose no sensor visited; and the sensor's path, from which a sweep is rendered
in time sectors (rolling shutter, omnire/rollingshutter.py). Conventions: docs/lidar.md.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from omnire.beams import points_in_sensor_frame, range_image, spherical
from omnire.data.scene import BeamModel, SceneData
from omnire.errors import UserError
from omnire.interpolation import interpolate_poses
from omnire.rollingshutter import SweepSector, sweep_sectors


@dataclasses.dataclass(frozen=True)
class SensorPath:
    """The sensor's pose over time: ``poses`` (K, 4, 4) sensor-to-world known at increasing
    ``times`` (K,) seconds on the log's clock, interpolated between them (rotation SLERP,
    translation linear) and held outside."""

    times: np.ndarray
    poses: np.ndarray

    def at(self, t) -> np.ndarray:
        """(Q, 4, 4) poses at the times ``t`` (Q,)."""
        return interpolate_poses(self.times, self.poses, np.atleast_1d(np.asarray(t, dtype=np.float64)))


@dataclasses.dataclass
class SweepRays:
    """R rays of one sweep, in the sensor frame at each ray's own time.

    Attributes:
        azimuth_deg, elevation_deg: (R,) float64 direction (omnire.beams.spherical).
        times: (R,) float64 seconds on the log's clock at which each ray was fired.
        range: (R,) float64 metres measured, NaN where the ray returned nothing or nothing
            was measured (a new pose).
        intensity: (R,) float32 measured intensity, NaN where none (or not recorded).
        returned: (R,) bool: the ray came back.
        beam: (R,) int16 beam index, -1 where unknown.
        drops_known: the rays that did not return are the sweep's real missing returns
            (its beams are known), so a ray-drop model can learn from them.
        min_range, max_range: metres, the sensor's limits.
    """

    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    times: np.ndarray
    range: np.ndarray
    intensity: np.ndarray
    returned: np.ndarray
    beam: np.ndarray
    drops_known: bool
    min_range: float
    max_range: float

    def __len__(self) -> int:
        return len(self.azimuth_deg)

    def select(self, rows: np.ndarray) -> "SweepRays":
        """The rays ``rows`` (indices or a (R,) bool mask)."""
        per_ray = {f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)
                   if isinstance(getattr(self, f.name), np.ndarray)}
        return dataclasses.replace(self, **per_ray)

    def directions(self) -> np.ndarray:
        """(R, 3) unit directions in the sensor frame."""
        az, el = np.deg2rad(self.azimuth_deg), np.deg2rad(self.elevation_deg)
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


def sensor_path(scene: SceneData) -> SensorPath:
    """The LiDAR's pose at any time: its recorded per-frame poses interpolated (rotation SLERP,
    translation linear; clamped outside the log). A dataset that records only the sensor's
    origins gets a sensor with the world's axes at them: ray directions are then measured in
    those axes, consistently for the recorded sweeps and their renders (a beam model, which
    needs the true axes, comes only with real poses). Raises :class:`UserError` for a scene
    without LiDAR."""
    lidar = scene.lidar
    if lidar is None:
        raise UserError(f"scene {scene.name!r} has no LiDAR")
    have = np.array([p is not None for p in lidar.points], dtype=bool)
    times = np.asarray(scene.frame_timestamps, dtype=np.float64)[have]
    if lidar.sensor_to_world is not None:
        poses = np.asarray(lidar.sensor_to_world, dtype=np.float64)[have]
    else:
        poses = np.tile(np.eye(4), (int(have.sum()), 1, 1))
        poses[:, :3, 3] = np.asarray(lidar.origins, dtype=np.float64)[have]
    return SensorPath(times, poses)


def recorded_sweep(scene: SceneData, frame: int) -> Optional[SweepRays]:
    """The rays of frame ``frame``'s sweep: one per return (its direction from the sensor at
    its own time, its range and intensity), and, when the sweep's beams and beam model are
    known, one per missing return of its range image (omnire.beams.range_image), fired at
    the time interpolated between the returns on either side of its azimuth. None when the
    frame has no LiDAR."""
    lidar = scene.lidar
    if lidar is None or lidar.points[frame] is None:
        return None
    points = lidar.points[frame]
    frame_time = float(scene.frame_timestamps[frame])
    times = (lidar.times[frame].astype(np.float64) if lidar.times is not None
             else np.full(len(points), frame_time))
    path = sensor_path(scene)
    pose_times = np.unique(np.concatenate([times, [frame_time]])) if len(times) else np.array([frame_time])
    local = points_in_sensor_frame(points, times, pose_times, path.at(pose_times))
    rng, az, el = spherical(local)
    intensity = (lidar.intensity[frame].astype(np.float32) if lidar.intensity is not None
                 else np.full(len(points), np.nan, np.float32))
    beam = lidar.beams[frame].astype(np.int16) if lidar.beams is not None else np.full(len(points), -1, np.int16)
    model = lidar.beam_model
    if model is not None:
        limits = (float(model.min_range), float(model.max_range))
    else:  # no sensor model: anything out to half again the farthest return
        limits = (0.0, 1.5 * float(rng.max(initial=1.0)))
    sweep = SweepRays(az, el, times, rng, intensity, np.ones(len(points), bool), beam, False, *limits)
    if lidar.beams is None or model is None or not len(points):
        return sweep
    image = range_image(rng, az, beam, model)
    b, col = np.nonzero(~image.returned)
    miss_az = (image.azimuth_offset_deg[b] + col * (360.0 / model.num_azimuths)) % 360.0
    order = np.argsort(az)
    miss_t = np.interp(miss_az, az[order], times[order], period=360.0)
    n = len(b)
    return SweepRays(np.concatenate([az, miss_az]), np.concatenate([el, model.elevations_deg[b]]),
                     np.concatenate([times, miss_t]), np.concatenate([rng, np.full(n, np.nan)]),
                     np.concatenate([intensity, np.full(n, np.nan, np.float32)]),
                     np.concatenate([sweep.returned, np.zeros(n, bool)]),
                     np.concatenate([beam, b.astype(np.int16)]), True, *limits)


def beam_model_sweep(model: BeamModel, time: float) -> SweepRays:
    """Every ray of one revolution of ``model`` (beam-major), all fired at ``time``; nothing
    measured."""
    B, A = model.num_beams, model.num_azimuths
    az = np.tile(np.arange(A) * (360.0 / A), B)
    el = np.repeat(model.elevations_deg, A)
    R = B * A
    return SweepRays(az, el, np.full(R, float(time)), np.full(R, np.nan), np.full(R, np.nan, np.float32),
                     np.zeros(R, bool), np.repeat(np.arange(B, dtype=np.int16), A), False,
                     float(model.min_range), float(model.max_range))


def shifted_path(path: SensorPath, offset: np.ndarray) -> SensorPath:
    """``path`` with the sensor moved by ``offset`` (3,) metres in its own frame (x forward,
    y left, z up)."""
    move = np.eye(4)
    move[:3, 3] = offset
    return SensorPath(path.times, path.poses @ move)


def fixed_path(sensor_to_world: np.ndarray) -> SensorPath:
    """A sensor standing at ``sensor_to_world`` (4, 4) at every time."""
    return SensorPath(np.zeros(1), np.asarray(sensor_to_world, dtype=np.float64)[None])


def sectors_of(sweep: SweepRays, path: SensorPath, sectors: int, device: torch.device | str = "cpu",
               dtype: torch.dtype = torch.float32) -> list[SweepSector]:
    """The rays of ``sweep`` in ``sectors`` time sectors, each cast from ``path``'s pose at its
    middle time (:func:`omnire.rollingshutter.sweep_sectors`)."""
    return sweep_sectors(torch.as_tensor(sweep.azimuth_deg, dtype=dtype, device=device),
                         torch.as_tensor(sweep.elevation_deg, dtype=dtype, device=device), sweep.times,
                         path.times, path.poses, sweep.min_range, sweep.max_range, sectors)
