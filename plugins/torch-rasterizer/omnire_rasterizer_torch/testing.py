"""Test helpers: a brute-force LiDAR renderer (numpy float64: every ray against every
Gaussian in order of centre distance, with the Jacobian of the spherical map taken by
central differences and S^-1 by matrix inversion, independent of omnire's projection,
tiles and torch) and LiDAR scene builders. Used by this plugin's tests and the cpu
rasterizer's."""
from __future__ import annotations

import numpy as np
import torch

ALPHA_MIN, ALPHA_MAX, T_MIN = 1.0 / 255.0, 0.99, 1e-4


def rotmats(quats: np.ndarray) -> np.ndarray:
    """(N, 4) wxyz, any norm (zero = identity) -> (N, 3, 3)."""
    q = np.asarray(quats, dtype=np.float64).copy()
    n = np.linalg.norm(q, axis=1)
    q[n == 0] = [1.0, 0.0, 0.0, 0.0]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def angles(p: np.ndarray) -> np.ndarray:
    """(..., 3) sensor-frame points -> (..., 2) azimuth in [0, 360), elevation, degrees."""
    az = np.degrees(np.arctan2(p[..., 1], p[..., 0])) % 360.0
    el = np.degrees(np.arctan2(p[..., 2], np.hypot(p[..., 0], p[..., 1])))
    return np.stack([az, el], -1)


def wrap(x):
    return (x + 180.0) % 360.0 - 180.0


def brute_force(means, quats, scales, opacities, features, pose, azimuth, elevation, min_range, max_range,
                eps_deg2=0.01, range_of="max_response", probe=None):
    """The contract of ``rasterize_lidar`` evaluated ray by ray. ``range_of`` "max_response"
    (the contract) or "centre" (the centre distance, for comparison). Returns range (R,),
    median_range (R,), features (R, F), alpha (R,), and with ``probe`` (R,) ranges the
    transmittance at them (R,) as a fifth."""
    means, scales, features = (np.asarray(x, dtype=np.float64) for x in (means, scales, features))
    opacities = np.asarray(opacities, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    Rs, ts = pose[:3, :3], pose[:3, 3]
    m = (means - ts) @ Rs  # sensor frame
    rho = np.linalg.norm(m, axis=1)
    centre = angles(m)
    rot = Rs.T @ rotmats(quats)
    S = rot @ (scales[:, :, None] ** 2 * np.swapaxes(rot, 1, 2))  # (N, 3, 3) sensor-frame covariance
    J = np.zeros((len(m), 2, 3))
    for k in range(3):
        h = np.zeros(3)
        h[k] = 1e-6
        diff = angles(m + h) - angles(m - h)
        diff[:, 0] = wrap(diff[:, 0])
        J[:, :, k] = diff / 2e-6
    cov = J @ S @ np.swapaxes(J, 1, 2) + eps_deg2 * np.eye(2)
    conic = np.linalg.inv(cov)
    drawn = (rho > min_range) & (rho < max_range) & (np.abs(centre[:, 1]) < 89.0) & (opacities >= ALPHA_MIN)
    order = np.argsort(rho, kind="stable")
    order = order[drawn[order]]
    S_inv = np.linalg.inv(S[order])
    m_o, c_o, o_o, f_o, con_o = m[order], centre[order], opacities[order], features[order], conic[order]
    az = np.asarray(azimuth, dtype=np.float64)
    el = np.asarray(elevation, dtype=np.float64)
    n_rays = len(az)
    out_range, out_median = np.zeros(n_rays), np.full(n_rays, float(max_range))
    out_feat, out_alpha = np.zeros((n_rays, features.shape[1])), np.zeros(n_rays)
    out_light = np.ones(n_rays)
    for j in range(n_rays):
        a, e = np.radians(az[j]), np.radians(el[j])
        d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        T, wsum, rsum, fsum, median = 1.0, 0.0, 0.0, np.zeros(features.shape[1]), None
        off = np.stack([wrap(az[j] - c_o[:, 0]), el[j] - c_o[:, 1]], -1)  # (M, 2)
        alphas = np.minimum(ALPHA_MAX, o_o * np.exp(-0.5 * np.einsum("mi,mij,mj->m", off, con_o, off)))
        for i in np.flatnonzero(alphas >= ALPHA_MIN):  # the others are skipped, whatever their range
            alpha = alphas[i]
            r = (d @ S_inv[i] @ m_o[i]) / (d @ S_inv[i] @ d) if range_of == "max_response" else np.linalg.norm(m_o[i])
            if not (min_range <= r <= max_range):
                continue
            if T * (1 - alpha) <= T_MIN:
                break
            w = alpha * T
            wsum, rsum, fsum = wsum + w, rsum + w * r, fsum + w * f_o[i]
            if median is None and T * (1 - alpha) <= 0.5:
                median = r
            if probe is not None and r < probe[j]:
                out_light[j] *= 1 - alpha
            T *= 1 - alpha
        out_range[j] = rsum / max(wsum, 1e-10)
        out_median[j] = max_range if median is None else median
        out_feat[j], out_alpha[j] = fsum, wsum
    if probe is not None:
        return out_range, out_median, out_feat, out_alpha, out_light
    return out_range, out_median, out_feat, out_alpha


def random_lidar_scene(n: int, n_rays: int, seed: int, dtype=torch.float64, features: int = 2):
    """N Gaussians at 3-20 m around a moved and turned sensor, within +-20 degrees of its
    horizon, and ``n_rays`` random rays in that band (some straddling azimuth 0). Returns a
    dict: means, quats, scales, opacities, colors (the features), pose (4, 4), azimuth,
    elevation (tensors of ``dtype``)."""
    g = np.random.default_rng(seed)
    yaw = g.uniform(0, 2 * np.pi)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    pose[:3, 3] = g.normal(size=3) * 3
    rng = g.uniform(3, 20, n)
    az = g.uniform(0, 360, n)
    el = g.uniform(-20, 20, n)
    az[: n // 8] = g.uniform(-3, 3, n // 8) % 360  # near the seam
    p = rng[:, None] * np.stack([np.cos(np.radians(el)) * np.cos(np.radians(az)),
                                 np.cos(np.radians(el)) * np.sin(np.radians(az)), np.sin(np.radians(el))], -1)
    means = p @ pose[:3, :3].T + pose[:3, 3]
    quats = g.normal(size=(n, 4))
    scales = rng[:, None] * 0.03 * np.exp(0.6 * g.normal(size=(n, 3)))
    opac = g.uniform(0.05, 0.9, n)
    colors = g.uniform(0, 1, (n, features))
    ray_az = g.uniform(0, 360, n_rays)
    ray_az[: n_rays // 4] = g.uniform(-3, 3, n_rays // 4)  # around the seam, some negative
    ray_el = g.uniform(-20, 20, n_rays)
    t = lambda x: torch.tensor(x, dtype=dtype)  # noqa: E731
    return dict(means=t(means), quats=t(quats), scales=t(scales), opacities=t(opac), colors=t(colors), pose=t(pose),
                azimuth=t(ray_az), elevation=t(ray_el))


def flat_grid(x: np.ndarray, y: np.ndarray, z: float, sigma: float, thickness: float = 1e-3, opacity: float = 0.9):
    """Flat Gaussians (normal +z) on the grid x (X,) by y (Y,) at height z: means (M, 3),
    quats (M, 4) identity, scales (M, 3), opacities (M,)."""
    X, Y = np.meshgrid(x, y, indexing="ij")
    means = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], -1)
    M = len(means)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (M, 1))
    scales = np.tile([sigma, sigma, thickness], (M, 1))
    return means, quats, scales, np.full(M, opacity)
