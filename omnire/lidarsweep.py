"""The rays of one LiDAR sweep and what came back along them: the recorded sweep of a frame
(returns, plus the missing returns where the scene knows its beams), or every ray of a beam
model from a pose no sensor visited; and the sensor's path, from which a sweep is rendered
in time sectors (rolling shutter, omnire/rollingshutter.py) and along which a recorded
sweep's rays start in the world (the sensor moves ~1 m during a sweep at 36 km/h). The same
rays are what training fits (omnire/lidartraining.py) and what a held-out sweep is scored on
(omnire/lidar_metrics.py, omnire/lidar_baselines.py). Conventions: docs/lidar.md.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from omnire.beams import points_in_sensor_frame, range_image, spherical
from omnire.data.scene import BeamModel, SceneData, SceneDataError
from omnire.errors import UserError
from omnire.interpolation import extend_poses, interpolate_poses
from omnire.rollingshutter import SweepSector, sector_split, sweep_sectors


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


def _unit_vectors(azimuth_deg: np.ndarray, elevation_deg: np.ndarray) -> np.ndarray:
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


@dataclasses.dataclass
class SweepRays:
    """R rays of one sweep, each in the sensor frame at its own time.

    Attributes:
        azimuth_deg, elevation_deg: (R,) float64 direction (omnire.beams.spherical).
        times: (R,) float64 seconds on the log's clock at which each ray was fired.
        range: (R,) float64 metres measured, NaN where the ray returned nothing or nothing
            was measured (a new pose).
        intensity: (R,) float32 measured intensity, NaN where none (or not recorded).
        returned: (R,) bool: the ray came back.
        beam: (R,) int16 beam index, -1 where unknown.
        column: (R,) int64 azimuth bin of the range image, -1 off the beam grid.
        drops_known: the rays that did not return are the sweep's real missing returns
            (its beams are known), so a ray-drop model can learn from them.
        min_range, max_range: metres, the sensor's limits.
        origins, directions: (R, 3) float64 world position of the sensor when the ray fired
            and the ray's unit world direction, for a recorded sweep (from the sensor path
            it was recorded along); None for rays of a pose no sensor visited.
        depth_edge: (R,) bool, the returns at a depth edge (:func:`depth_edges`); None when
            not measured.
    """

    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    times: np.ndarray
    range: np.ndarray
    intensity: np.ndarray
    returned: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    drops_known: bool
    min_range: float
    max_range: float
    origins: Optional[np.ndarray] = None
    directions: Optional[np.ndarray] = None
    depth_edge: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.azimuth_deg)

    def select(self, rows: np.ndarray) -> "SweepRays":
        """The rays ``rows`` (indices or a (R,) bool mask)."""
        per_ray = {f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)
                   if isinstance(getattr(self, f.name), np.ndarray)}
        return dataclasses.replace(self, **per_ray)

    @property
    def local_directions(self) -> np.ndarray:
        """(R, 3) unit directions in the sensor frame (x forward, y left, z up)."""
        return _unit_vectors(self.azimuth_deg, self.elevation_deg)

    def points(self) -> np.ndarray:
        """(P, 3) world points of the returns (a recorded sweep's)."""
        if self.origins is None:
            raise SceneDataError("SweepRays.points: the rays have no world origins (not a recorded sweep)")
        ok = self.returned
        return self.origins[ok] + self.directions[ok] * self.range[ok, None]


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
               model: Optional[BeamModel] = None, grid_only: bool = True) -> SweepRays:
    """The rays of one recorded sweep, with their world origins and directions.

    Args:
        points: (N, 3) world returns; times: (N,) their times (log clock, seconds).
        pose_times, sensor_to_world: the sensor's track, (K,) increasing seconds and (K, 4, 4)
            poses (x-forward axes), interpolated at each ray's time.
        intensity: optional (N,) recorded intensity.
        beams, model: optional (N,) beam per return (-1 = another sensor) and the
            :class:`BeamModel`; with both, the rays are every cell of the range image
            (omnire.beams.range_image), beam-major, an empty cell (a missing return) fired
            at its azimuth column's time (median time of that column's returns) along its
            beam's elevation at the column's azimuth. Without, one ray per return, in order.
        grid_only: with a beam model, leave out the returns that are in no cell of the
            range image (another sensor's, or a second return in a cell); else they follow
            the grid, with column -1.
    """
    points = np.asarray(points, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    n = len(points)
    if points.shape != (n, 3) or times.shape != (n,) or (intensity is not None and np.shape(intensity) != (n,)):
        raise SceneDataError(f"sweep_rays: points {points.shape}, times {times.shape}, intensity "
                             f"{None if intensity is None else np.shape(intensity)}; expected (N, 3), (N,), (N,)")
    value = np.full(n, np.nan, dtype=np.float32) if intensity is None else np.asarray(intensity, dtype=np.float32)
    beam = np.full(n, -1, np.int16) if beams is None else np.asarray(beams).astype(np.int16)
    rng, az, el = spherical(points_in_sensor_frame(points, times, pose_times, sensor_to_world))
    if model is not None:
        limits = (float(model.min_range), float(model.max_range))
    else:  # no sensor model: anything out to half again the farthest return
        limits = (0.0, 1.5 * float(rng.max(initial=1.0)))
    if beams is None or model is None or not n:
        rays = SweepRays(az, el, times, rng, value, np.ones(n, bool), beam, np.full(n, -1, np.int64), False, *limits)
        return _in_world(rays, pose_times, sensor_to_world)
    image = range_image(rng, az, beam, model)
    B, A = model.num_beams, model.num_azimuths
    cell = image.point.reshape(-1)  # (B * A,) return index or -1
    hit = cell >= 0
    cell_time = np.full(B * A, np.nan)
    cell_time[hit] = times[cell[hit]]
    t = np.repeat(_column_times(cell_time.reshape(B, A))[None], B, 0).reshape(-1)
    t[hit] = times[cell[hit]]
    grid_beam = np.repeat(np.arange(B), A)
    column = np.tile(np.arange(A), B)
    cell_az = (image.azimuth_offset_deg[grid_beam] + column * (360.0 / A)) % 360.0
    cell_el = model.elevations_deg[grid_beam].astype(np.float64)
    cell_az[hit], cell_el[hit] = az[cell[hit]], el[cell[hit]]
    rest = np.zeros(0, np.int64) if grid_only else np.setdiff1d(np.arange(n), cell[hit])

    def joined(per_return: np.ndarray) -> np.ndarray:
        """(N,) per return -> (R,) per ray, NaN at the missing returns."""
        out = np.full(B * A, np.nan, dtype=per_return.dtype)
        out[hit] = per_return[cell[hit]]
        return np.concatenate([out, per_return[rest]])

    rays = SweepRays(np.concatenate([cell_az, az[rest]]), np.concatenate([cell_el, el[rest]]),
                     np.concatenate([t, times[rest]]), joined(rng), joined(value),
                     np.concatenate([hit, np.ones(len(rest), bool)]),
                     np.concatenate([grid_beam.astype(np.int16), beam[rest]]),
                     np.concatenate([column, np.full(len(rest), -1, np.int64)]), True, *limits)
    return _in_world(rays, pose_times, sensor_to_world)


def _in_world(rays: SweepRays, pose_times: np.ndarray, sensor_to_world: np.ndarray) -> SweepRays:
    """``rays`` with their world origins and directions (the track's pose at each ray's time)."""
    pose = interpolate_poses(pose_times, sensor_to_world, rays.times)  # (R, 4, 4)
    directions = np.einsum("rij,rj->ri", pose[:, :3, :3], rays.local_directions)
    return dataclasses.replace(rays, origins=pose[:, :3, 3], directions=directions)


TRACK_MARGIN_S = 0.2
"""Seconds the sensor path is extrapolated past the first and last sweep (a sweep starts
one revolution, ~0.1 s, before its frame's timestamp)."""


def sensor_path(scene: SceneData) -> SensorPath:
    """The LiDAR's pose at any time: its recorded poses at the frames with LiDAR, interpolated
    (rotation SLERP, translation linear), extrapolated at constant velocity
    :data:`TRACK_MARGIN_S` past both ends (with two frames or more) and held beyond. A dataset
    that records only the sensor's origins gets a sensor with the world's axes at them: ray
    directions are then measured in those axes, consistently for the recorded sweeps and
    their renders (a beam model, which needs the true axes, comes only with real poses).
    Raises :class:`UserError` for a scene without LiDAR."""
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
    return SensorPath(*extend_poses(times, poses, TRACK_MARGIN_S)) if len(times) >= 2 else SensorPath(times, poses)


def recorded_sweep(scene: SceneData, frame: int, grid_only: bool = False) -> Optional[SweepRays]:
    """The rays of frame ``frame``'s sweep (:func:`sweep_rays` with what the scene records:
    per-point times, else the frame's timestamp; intensity; beams and beam model; the
    :func:`sensor_path`). ``grid_only``: with a beam model, only the cells of the range
    image (the rays a held-out sweep is scored on); else every return too (the rays
    training fits). None when the frame has no LiDAR."""
    lidar = scene.lidar
    if lidar is None or lidar.points[frame] is None:
        return None
    points = lidar.points[frame]
    times = (lidar.times[frame] if lidar.times is not None
             else np.full(len(points), float(scene.frame_timestamps[frame])))
    path = sensor_path(scene)
    return sweep_rays(points, times, path.times, path.poses,
                      intensity=None if lidar.intensity is None else lidar.intensity[frame],
                      beams=None if lidar.beams is None else lidar.beams[frame], model=lidar.beam_model,
                      grid_only=grid_only)


def depth_edges(sweep: SweepRays, model: BeamModel, relative_jump: float) -> np.ndarray:
    """(R,) bool: the returns of ``sweep`` at a depth edge of its range image, where a ray
    may graze one surface and return from another behind it.

    A return on the beam grid (``column`` >= 0) is at an edge when one of its four grid
    neighbours (the adjacent azimuth columns of its beam, wrapping round; the beams just
    above and below it in elevation, same column) returned nothing, or returned at a range
    differing from its own by more than ``relative_jump`` times its own range; a neighbour
    off the top or bottom beam does not count. A return off the grid (a second return in an
    occupied cell) is always at an edge. Rays that did not return are False.
    """
    B, A = model.num_beams, model.num_azimuths
    returned = np.asarray(sweep.returned, dtype=bool)
    on_grid = returned & (sweep.column >= 0)
    row_of_beam = np.empty(B, dtype=np.int64)
    row_of_beam[np.argsort(-model.elevations_deg, kind="stable")] = np.arange(B)  # row 0: the top beam
    rows, cols = row_of_beam[sweep.beam[on_grid].astype(np.int64)], sweep.column[on_grid]
    image = np.full((B, A), np.nan)  # (B, A) range, NaN where nothing returned
    image[rows, cols] = sweep.range[on_grid]
    r = image[rows, cols]
    edge = np.zeros(len(r), dtype=bool)
    for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
        nr = rows + dr
        inside = (nr >= 0) & (nr < B)
        other = image[np.clip(nr, 0, B - 1), (cols + dc) % A]
        edge |= inside & ~(np.abs(other - r) <= relative_jump * r)  # NaN (no return) counts as an edge
    out = returned & (sweep.column < 0)
    out[np.flatnonzero(on_grid)] = edge
    return out


def beam_model_sweep(model: BeamModel, time: float) -> SweepRays:
    """Every ray of one revolution of ``model`` (beam-major), all fired at ``time``; nothing
    measured."""
    B, A = model.num_beams, model.num_azimuths
    az = np.tile(np.arange(A) * (360.0 / A), B)
    el = np.repeat(model.elevations_deg, A)
    R = B * A
    return SweepRays(az, el, np.full(R, float(time)), np.full(R, np.nan), np.full(R, np.nan, np.float32),
                     np.zeros(R, bool), np.repeat(np.arange(B, dtype=np.int16), A), np.tile(np.arange(A), B),
                     False, float(model.min_range), float(model.max_range))


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
               dtype: torch.dtype = torch.float32, probe_range: Optional[np.ndarray] = None) -> list[SweepSector]:
    """The rays of ``sweep`` in ``sectors`` time sectors, each cast from ``path``'s pose at its
    middle time (:func:`omnire.rollingshutter.sweep_sectors`), with ``probe_range`` (R,)
    metres per ray when given."""
    probe = None if probe_range is None else torch.as_tensor(probe_range, dtype=dtype, device=device)
    return sweep_sectors(torch.as_tensor(sweep.azimuth_deg, dtype=dtype, device=device),
                         torch.as_tensor(sweep.elevation_deg, dtype=dtype, device=device), sweep.times,
                         path.times, path.poses, sweep.min_range, sweep.max_range, sectors, probe)


def aimed_from_sectors(sweep: SweepRays, path: SensorPath, sectors: int) -> SweepRays:
    """A recorded ``sweep`` with each ray re-aimed from the pose :func:`sectors_of` casts it
    from (the sensor at its sector's middle time) instead of the pose it was fired from: a
    returned ray points at its recorded return and measures the distance to it from there;
    a missing return keeps its world direction. Rendered with the same ``sectors``, a static
    surface is then fitted where it was measured, whatever the sector's duration (the
    sensor moves ~0.5 m during a sweep at 18 km/h, so the unaimed rays of 4 sectors start up
    to 6 cm off their recorded origin); only what moves within a sector (actors) stays
    approximate. A sweep without world origins (a pose no sensor visited) is returned as it is."""
    if sweep.origins is None or not len(sweep):
        return sweep
    which, middles = sector_split(sweep.times, sectors)
    pose = path.at(middles)[which]  # (R, 4, 4) the pose each ray is cast from
    rotation, origin = pose[:, :3, :3], pose[:, :3, 3]
    ok = sweep.returned
    world = sweep.directions.copy()  # (R, 3) unit world directions; returned rays towards their returns
    world[ok] = sweep.origins[ok] + sweep.directions[ok] * sweep.range[ok, None] - origin[ok]
    rng, az, el = spherical(np.einsum("rji,rj->ri", rotation, world))  # in the casting pose's frame
    return dataclasses.replace(sweep, azimuth_deg=az, elevation_deg=el, range=np.where(ok, rng, np.nan),
                               origins=origin, directions=world / rng[:, None])
