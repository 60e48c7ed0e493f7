"""Procedural, tileable textures for the synthetic street (deterministic from a seed).

Every material is one (T, T, 3) RGB texture in [0, 1] plus a LiDAR reflectivity. Meshes
carry UVs in texture repeats, so a texture's physical size is set where the UVs are made.
"""
from __future__ import annotations

import numpy as np

TEX = 128

# name -> index; the order is fixed so scenes stay reproducible.
MATERIALS = (
    "asphalt", "marking", "marking_yellow", "paving", "curb",
    "facade0", "facade1", "facade2", "facade3", "facade4",
    "trunk", "foliage", "metal", "glass", "tire", "barrier", "noise_wall", "grass",
    "paint0", "paint1", "paint2", "paint3", "paint4", "paint5",
    "skin", "shirt0", "shirt1", "shirt2", "shirt3", "shirt4", "pants0", "pants1", "pants2", "pants3",
    "bike", "spokes",
)
MAT = {name: i for i, name in enumerate(MATERIALS)}
PAINTS = [MAT[f"paint{i}"] for i in range(6)]
SHIRTS = [MAT[f"shirt{i}"] for i in range(5)]
PANTS = [MAT[f"pants{i}"] for i in range(4)]
FACADES = [MAT[f"facade{i}"] for i in range(5)]

REFLECTIVITY = {
    "asphalt": 0.12, "marking": 0.8, "marking_yellow": 0.7, "paving": 0.3, "curb": 0.35,
    "trunk": 0.2, "foliage": 0.25, "metal": 0.5, "glass": 0.08, "tire": 0.05, "barrier": 0.4,
    "noise_wall": 0.3, "grass": 0.3, "skin": 0.3, "bike": 0.45, "spokes": 0.4,
}


def _noise(rng: np.random.Generator, beta: float = 2.0, T: int = TEX) -> np.ndarray:
    """Tileable 1/f^beta noise in [0, 1], shape (T, T) (periodic by construction via FFT)."""
    white = rng.normal(size=(T, T))
    fy = np.fft.fftfreq(T)[:, None]
    fx = np.fft.fftfreq(T)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = 1.0
    spec = np.fft.fft2(white) / f ** (beta / 2.0)
    spec[0, 0] = 0.0
    n = np.real(np.fft.ifft2(spec))
    n = (n - n.min()) / max(np.ptp(n), 1e-9)
    return n


def _tint(base, noise: np.ndarray, amount: float) -> np.ndarray:
    base = np.asarray(base, dtype=np.float64)
    return np.clip(base[None, None, :] * (1.0 - amount + 2.0 * amount * noise[..., None]), 0.0, 1.0)


def _facade(rng: np.random.Generator, wall, glass, T: int = TEX) -> np.ndarray:
    """One window bay of one floor (3 m x 3 m): wall, a window with frame and sill."""
    tex = _tint(wall, _noise(rng, 1.5), 0.12)
    yy, xx = np.mgrid[0:T, 0:T] / T  # v (row) = height fraction from the top
    win = (xx > 0.22) & (xx < 0.78) & (yy > 0.25) & (yy < 0.72)
    frame = (xx > 0.19) & (xx < 0.81) & (yy > 0.22) & (yy < 0.75) & ~win
    sill = (xx > 0.17) & (xx < 0.83) & (yy >= 0.75) & (yy < 0.79)
    mullion = win & (np.abs(xx - 0.5) < 0.012)
    grad = 0.6 + 0.4 * (1.0 - yy)  # sky reflection brighter at the top of the pane
    glass_c = np.asarray(glass)[None, None, :] * grad[..., None]
    tex[win] = glass_c[win]
    tex[frame | mullion] = np.array([0.92, 0.92, 0.9])
    tex[sill] = np.asarray(wall) * 0.7
    return tex


def build_textures(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """All material textures (M, T, T, 3) float32 and reflectivities (M,) float32."""
    rng = np.random.default_rng(seed + 7919)
    T = TEX
    out = np.zeros((len(MATERIALS), T, T, 3))
    yy, xx = np.mgrid[0:T, 0:T] / T
    out[MAT["asphalt"]] = _tint([0.33, 0.33, 0.34], _noise(rng, 1.0) * 0.6 + 0.4 * _noise(rng, 2.5), 0.25)
    out[MAT["marking"]] = _tint([0.93, 0.93, 0.9], _noise(rng, 1.0), 0.05)
    out[MAT["marking_yellow"]] = _tint([0.9, 0.75, 0.2], _noise(rng, 1.0), 0.05)
    paving = _tint([0.62, 0.6, 0.56], _noise(rng, 1.5), 0.12)
    joints = (np.abs((xx * 2) % 1.0 - 0.5) > 0.47) | (np.abs((yy * 2) % 1.0 - 0.5) > 0.47)
    paving[joints] *= 0.6
    out[MAT["paving"]] = paving
    out[MAT["curb"]] = _tint([0.7, 0.7, 0.68], _noise(rng, 2.0), 0.1)
    walls = [[0.76, 0.62, 0.48], [0.55, 0.32, 0.25], [0.82, 0.8, 0.74], [0.45, 0.5, 0.55], [0.7, 0.68, 0.52]]
    glasses = [[0.25, 0.35, 0.45], [0.2, 0.26, 0.3], [0.3, 0.38, 0.42], [0.18, 0.22, 0.3], [0.28, 0.3, 0.36]]
    for i, (w, g) in enumerate(zip(walls, glasses)):
        out[MAT[f"facade{i}"]] = _facade(rng, w, g)
    bark = _tint([0.35, 0.26, 0.18], _noise(rng, 1.2), 0.3)
    bark *= (0.8 + 0.2 * np.sin(xx * 2 * np.pi * 8))[..., None]
    out[MAT["trunk"]] = bark
    leaves = _noise(rng, 0.8)
    out[MAT["foliage"]] = np.clip(
        np.stack([0.12 + 0.2 * leaves, 0.3 + 0.35 * leaves, 0.08 + 0.12 * leaves], -1), 0, 1
    )
    out[MAT["metal"]] = _tint([0.45, 0.47, 0.5], _noise(rng, 2.0), 0.08)
    out[MAT["glass"]] = _tint([0.12, 0.16, 0.2], _noise(rng, 2.5), 0.2)
    out[MAT["tire"]] = _tint([0.07, 0.07, 0.08], _noise(rng, 1.5), 0.3)
    barrier = _tint([0.72, 0.72, 0.7], _noise(rng, 1.5), 0.1)
    barrier[yy > 0.85] *= 0.7
    out[MAT["barrier"]] = barrier
    wall = _tint([0.45, 0.52, 0.42], _noise(rng, 1.5), 0.15)
    wall[np.abs((xx * 4) % 1.0 - 0.5) > 0.46] *= 0.55  # panel seams every 1 m (4 per repeat)
    out[MAT["noise_wall"]] = wall
    out[MAT["grass"]] = _tint([0.25, 0.42, 0.15], _noise(rng, 0.9), 0.3)
    paints = [[0.7, 0.08, 0.06], [0.1, 0.2, 0.55], [0.85, 0.85, 0.85], [0.1, 0.1, 0.1], [0.5, 0.52, 0.55], [0.85, 0.6, 0.1]]
    for i, c in enumerate(paints):
        p = _tint(c, _noise(rng, 2.5), 0.06)
        p[(yy > 0.48) & (yy < 0.52)] *= 0.75  # a trim line
        out[MAT[f"paint{i}"]] = p
    out[MAT["skin"]] = _tint([0.78, 0.6, 0.48], _noise(rng, 2.0), 0.08)
    shirts = [[0.8, 0.2, 0.2], [0.2, 0.45, 0.8], [0.9, 0.85, 0.3], [0.25, 0.6, 0.3], [0.9, 0.9, 0.9]]
    for i, c in enumerate(shirts):
        s = _tint(c, _noise(rng, 1.5), 0.15)
        if i % 2 == 0:  # stripes make motion and rotation visible
            s[((yy * 6) % 1.0) < 0.3] *= 0.6
        out[MAT[f"shirt{i}"]] = s
    pants = [[0.15, 0.18, 0.35], [0.2, 0.2, 0.2], [0.45, 0.38, 0.28], [0.3, 0.32, 0.36]]
    for i, c in enumerate(pants):
        out[MAT[f"pants{i}"]] = _tint(c, _noise(rng, 1.5), 0.12)
    out[MAT["bike"]] = _tint([0.1, 0.55, 0.25], _noise(rng, 2.0), 0.05)
    ang = np.arctan2(yy - 0.5, xx - 0.5)
    spokes = np.full((T, T, 3), 0.12)
    spokes[(np.abs(np.sin(ang * 4)) < 0.15)] = 0.75
    out[MAT["spokes"]] = spokes
    refl = np.array([REFLECTIVITY.get(n, 0.5 if n.startswith(("paint", "facade")) else 0.3) for n in MATERIALS])
    return out.astype(np.float32), refl.astype(np.float32)


def sky_color(elevation: np.ndarray) -> np.ndarray:
    """Sky gradient by view elevation sin (..., ) -> (..., 3) RGB: hazy horizon to blue zenith."""
    s = np.clip(elevation, 0.0, 1.0) ** 0.6
    horizon = np.array([0.85, 0.88, 0.92])
    zenith = np.array([0.3, 0.5, 0.85])
    return horizon * (1.0 - s[..., None]) + zenith * s[..., None]
