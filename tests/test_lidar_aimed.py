"""Re-aiming a recorded sweep's rays from the poses its sectors are rendered from
(omnire.lidarsweep.aimed_from_sectors): on a sensor driving over a sloping ground at 10 m/s,
each re-aimed returned ray cast from its sector's pose meets the ground exactly at its new
range (the unaimed ray misses it by centimetres), and a missing return keeps its direction."""
from __future__ import annotations

import numpy as np

from omnire.lidarsweep import SensorPath, aimed_from_sectors, sweep_rays
from omnire.rollingshutter import sector_split

HEIGHT = 1.9
SPEED = 10.0


def pose_at(t: np.ndarray) -> np.ndarray:
    """(T, 4, 4) sensor poses driving along +x and turning 10 degrees a second."""
    yaw = np.radians(10.0) * t
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    poses[:, :3, 3] = np.stack([SPEED * t, np.zeros_like(t), np.full_like(t, HEIGHT)], -1)
    return poses


NORMAL = np.array([0.05, 0.02, 1.0])
"""The ground: the plane NORMAL . x = 0, sloping up 5% along +x."""


def ground_range(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(R,) distance along each ray to the ground."""
    return -(origins @ NORMAL) / (directions @ NORMAL)


def test_aimed_rays_meet_the_ground_at_their_range():
    g = np.random.default_rng(0)
    R = 4000
    times = np.sort(g.uniform(0.0, 0.1, R))
    az, el = np.radians(g.uniform(0, 360, R)), np.radians(g.uniform(-25, -5, R))
    local = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    fired = pose_at(times)
    origins = fired[:, :3, 3]
    directions = np.einsum("rij,rj->ri", fired[:, :3, :3], local)
    points = origins + directions * ground_range(origins, directions)[:, None]
    path = SensorPath(np.linspace(-0.2, 0.3, 51), pose_at(np.linspace(-0.2, 0.3, 51)))
    sweep = sweep_rays(points, times, path.times, path.poses)
    sweep.returned[:100] = False  # missing returns: no range, a direction only
    sweep.range[:100] = np.nan
    for sectors in (1, 4):
        aimed = aimed_from_sectors(sweep, path, sectors)
        which, middles = sector_split(times, sectors)
        cast = path.at(middles)[which]
        np.testing.assert_allclose(aimed.origins, cast[:, :3, 3], atol=1e-12)
        ok = aimed.returned
        np.testing.assert_allclose(ground_range(aimed.origins[ok], aimed.directions[ok]), aimed.range[ok], rtol=1e-9)
        local_dirs = np.einsum("rji,rj->ri", cast[:, :3, :3], aimed.directions)  # the casting frame's
        np.testing.assert_allclose(local_dirs, aimed.local_directions, atol=1e-9)
        np.testing.assert_allclose(aimed.directions[:100], sweep.directions[:100], atol=1e-12)
        assert np.isnan(aimed.range[:100]).all()
        # the same rays cast unaimed (recorded azimuth and elevation from the sector's pose)
        unaimed = np.einsum("rij,rj->ri", cast[:, :3, :3], sweep.local_directions)
        miss = np.abs(ground_range(cast[ok, :3, 3], unaimed[ok]) - sweep.range[ok])
        assert miss.max() > 0.05, sectors
