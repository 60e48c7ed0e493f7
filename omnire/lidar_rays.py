"""The rays of a recorded LiDAR sweep: what a renderer is asked to render and what its
output is scored against (:mod:`omnire.lidar_metrics`, :mod:`omnire.lidar_baselines`).

With a beam model and the beam of each return, every cell of the sweep's range image
(:func:`omnire.beams.range_image`) is a ray, the empty cells being the missing returns
(ray drop); without, each return is a ray and missing returns are unknown. A ray starts
at the sensor's position at the time it fired (the sensor moves ~1 m during a sweep at
36 km/h) and points along its beam; conventions in docs/lidar.md.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from omnire.beams import points_in_sensor_frame, range_image, spherical
from omnire.data.scene import BeamModel, LidarSweeps, SceneDataError
from omnire.interpolation import extend_poses, interpolate_poses


@dataclasses.dataclass
class SweepRays:
    """R rays of one recorded sweep.

    Attributes:
        origins: (R, 3) float64 world position of the sensor when the ray fired.
        directions: (R, 3) float64 unit world directions.
        local_directions: (R, 3) float64 unit directions in the sensor frame at the ray's
            time (x forward, y left, z up).
        times: (R,) float64 seconds on the log's clock at which the ray fired.
        returned: (R,) bool; False = a missing return (only where ``drops_known``).
        range: (R,) float64 metres from the origin to the return, NaN where none.
        intensity: (R,) float32 recorded intensity, NaN where none or not recorded.
        beam: (R,) int64 beam index, -1 without a beam model.
        column: (R,) int64 azimuth bin, -1 without a beam model.
        drops_known: True when the rays are the full beam grid (missing returns known).
    """

    origins: np.ndarray
    directions: np.ndarray
    local_directions: np.ndarray
    times: np.ndarray
    returned: np.ndarray
    range: np.ndarray
    intensity: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    drops_known: bool

    def __len__(self) -> int:
        return len(self.times)

    def points(self) -> np.ndarray:
        """(P, 3) world points of the returns."""
        ok = self.returned
        return self.origins[ok] + self.directions[ok] * self.range[ok, None]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True).clip(1e-12)


def _column_times(cell_time: np.ndarray) -> np.ndarray:
    """(B, A) firing times with NaN at empty cells -> (A,) time of each azimuth column: the
    median over its returns, interpolated (periodically) over columns without any."""
    A = cell_time.shape[1]
    have = ~np.isnan(cell_time)
    col = np.full(A, np.nan)
    filled = have.any(axis=0)
    col[filled] = np.nanmedian(cell_time[:, filled], axis=0)
    if not filled.all():
        idx = np.flatnonzero(filled)
        col[~filled] = np.interp(np.flatnonzero(~filled), idx, col[idx], period=A)
    return col


def sweep_rays(points: np.ndarray, times: np.ndarray, pose_times: np.ndarray, sensor_to_world: np.ndarray,
               intensity: Optional[np.ndarray] = None, beams: Optional[np.ndarray] = None,
               model: Optional[BeamModel] = None) -> SweepRays:
    """The rays of one sweep.

    Args:
        points: (N, 3) world returns; times: (N,) their times (log clock, seconds).
        pose_times, sensor_to_world: the sensor's track, (K,) increasing seconds and (K, 4, 4)
            poses (x-forward axes), interpolated at each ray's time.
        intensity: optional (N,) recorded intensity.
        beams, model: optional (N,) beam per return (-1 = another sensor: left out) and the
            :class:`BeamModel`; with both, the rays are every cell of the range image, an
            empty cell's time being its azimuth column's (median time of that column's
            returns) and its direction its beam's elevation at the column's azimuth.
    """
    points = np.asarray(points, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    n = len(points)
    if points.shape != (n, 3) or times.shape != (n,) or (intensity is not None and np.shape(intensity) != (n,)):
        raise SceneDataError(f"sweep_rays: points {points.shape}, times {times.shape}, intensity "
                             f"{None if intensity is None else np.shape(intensity)}; expected (N, 3), (N,), (N,)")
    value = np.full(n, np.nan, dtype=np.float32) if intensity is None else np.asarray(intensity, dtype=np.float32)
    local = points_in_sensor_frame(points, times, pose_times, sensor_to_world)  # (N, 3)
    pose = interpolate_poses(pose_times, sensor_to_world, times)
    if beams is None or model is None:
        rng = np.linalg.norm(local, axis=1)
        none = np.full(n, -1, dtype=np.int64)
        return SweepRays(pose[:, :3, 3], _unit(points - pose[:, :3, 3]), _unit(local), times, np.ones(n, bool),
                         rng, value, none, none.copy(), drops_known=False)
    rng, az, _ = spherical(local)
    image = range_image(rng, az, np.asarray(beams), model)
    B, A = model.num_beams, model.num_azimuths
    cell = image.point.reshape(-1)  # (B * A,) return index or -1
    hit = cell >= 0
    cell_time = np.full(B * A, np.nan)
    cell_time[hit] = times[cell[hit]]
    t = np.repeat(_column_times(cell_time.reshape(B, A))[None], B, 0).reshape(-1)
    t[hit] = times[cell[hit]]
    beam = np.repeat(np.arange(B), A)
    column = np.tile(np.arange(A), B)
    step = 360.0 / A
    az_cell = np.deg2rad(image.azimuth_offset_deg[beam] + column * step)
    el_cell = np.deg2rad(model.elevations_deg[beam])
    d_local = np.stack([np.cos(el_cell) * np.cos(az_cell), np.cos(el_cell) * np.sin(az_cell), np.sin(el_cell)], 1)
    d_local[hit] = _unit(local[cell[hit]])
    cell_pose = interpolate_poses(pose_times, sensor_to_world, t)  # (R, 4, 4)
    origins = cell_pose[:, :3, 3]
    directions = np.einsum("rij,rj->ri", cell_pose[:, :3, :3], d_local)
    cell_range = np.full(B * A, np.nan)
    cell_range[hit] = rng[cell[hit]]
    cell_value = np.full(B * A, np.nan, dtype=np.float32)
    cell_value[hit] = value[cell[hit]]
    return SweepRays(origins, directions, d_local, t, hit, cell_range, cell_value, beam, column, drops_known=True)


TRACK_MARGIN_S = 0.2
"""Seconds the sensor track is extrapolated past the first and last sweep (a sweep starts
one revolution, ~0.1 s, before its frame's timestamp)."""


def lidar_track(lidar: LidarSweeps, frame_timestamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's poses over the frames with LiDAR, (K,) times and (K, 4, 4) poses,
    extrapolated at constant velocity :data:`TRACK_MARGIN_S` past both ends (with two
    frames or more). Needs ``lidar.sensor_to_world``."""
    if lidar.sensor_to_world is None:
        raise SceneDataError("lidar.sensor_to_world: not recorded; the sweep's rays need the sensor's poses")
    have = lidar.available_frames()
    times = np.asarray(frame_timestamps, dtype=np.float64)[have]
    poses = np.asarray(lidar.sensor_to_world, dtype=np.float64)[have]
    return extend_poses(times, poses, TRACK_MARGIN_S) if len(have) >= 2 else (times, poses)


def scene_sweep_rays(lidar: LidarSweeps, frame_timestamps: np.ndarray, frame: int) -> SweepRays:
    """The rays of the sweep of ``frame`` (:func:`sweep_rays` with what the scene records:
    per-point times, else the frame's timestamp; intensity; beams and beam model)."""
    points = lidar.points[frame]
    if points is None:
        raise SceneDataError(f"lidar.points[{frame}]: frame {frame} has no LiDAR sweep")
    times = (lidar.times[frame] if lidar.times is not None
             else np.full(len(points), float(frame_timestamps[frame])))
    known, poses = lidar_track(lidar, frame_timestamps)
    return sweep_rays(points, times, known, poses,
                      intensity=None if lidar.intensity is None else lidar.intensity[frame],
                      beams=None if lidar.beams is None else lidar.beams[frame], model=lidar.beam_model)
