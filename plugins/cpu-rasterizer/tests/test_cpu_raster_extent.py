"""The record's alpha extent and the tile lists: every pixel where a Gaussian reaches alpha
>= 1/255 (brute force in float64 over the whole image, from the record as stored) lies
inside the extent the kernel skips outside of, and, within the tiles of its 3-sigma radius
(which decides what is drawn, as in gsplat), in a tile whose list holds the Gaussian; and
that extent is the ellipse's own bounding box, not a padded one."""
from __future__ import annotations

import math

import pytest
import torch

from omnire.rasterization import RasterSettings
from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu._build import extension  # noqa: E402
from omnire_rasterizer_cpu.testing import random_scene  # noqa: E402

TILE = 16
W, H = 96, 80
TILES_X, TILES_Y = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE


def elongated_scene(seed: int) -> dict:
    """Small round, large round and thin tilted Gaussians (float32), opacities down to 0.01."""
    scene = random_scene(300, W, H, seed=seed, scale_px=3.0, opacity=(0.01, 0.99))
    g = torch.Generator().manual_seed(seed + 1)
    thin = torch.rand(300, generator=g) < 0.5
    scene["scales"][thin, 0] *= 12.0  # long axis
    scene["scales"][thin, 1] *= 0.08  # thin axis
    return {k: v.float() for k, v in scene.items()}


def forward(scene):
    s = RasterSettings()
    return extension().forward(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                               scene["viewmat"], scene["K"], W, H, s.near, s.far, s.eps2d, 1)


@pytest.mark.parametrize("seed", [0, 1])
def test_every_pixel_a_gaussian_reaches_is_inside_its_extent_and_tiles(seed):
    _acc, _dn, _alpha, radii, _m2d, rec, offsets, ids = forward(elongated_scene(seed))
    r = rec.double()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    col, row = xs.long() // TILE, ys.long() // TILE  # (H, W) tile column / row of each pixel
    tile_of = row * TILES_X + col
    checked = 0
    for i in torch.nonzero(radii > 0).flatten().tolist():
        mx, my, a, b, c, o = (float(v) for v in r[i, :6])
        ex, ey = float(r[i, 7]), float(r[i, 8])
        dx, dy = xs - mx, ys - my
        power = -0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy)
        reached = (o * torch.exp(power) >= 1.0 / 255.0) & (power <= 0)
        if not reached.any():
            continue
        checked += 1
        inside = (dx[reached].abs() <= ex).all() and (dy[reached].abs() <= ey).all()
        assert inside, f"Gaussian {i}: a pixel outside its extent"
        r3 = float(radii[i])  # the 3-sigma radius's tile rect, as the kernel computes it
        tx0, tx1 = max(0, math.floor((mx - r3) / TILE)), min(TILES_X, math.ceil((mx + r3) / TILE))
        ty0, ty1 = max(0, math.floor((my - r3) / TILE)), min(TILES_Y, math.ceil((my + r3) / TILE))
        in_rect = (col >= tx0) & (col < tx1) & (row >= ty0) & (row < ty1)
        for t in torch.unique(tile_of[reached & in_rect]).tolist():
            assert i in ids[offsets[t]:offsets[t + 1]].tolist(), f"Gaussian {i} missing from the list of tile {t}"
    assert checked > 200


def test_extent_is_the_bounding_box_of_the_alpha_ellipse():
    """ex = sqrt(tq cov_xx), ey = sqrt(tq cov_yy) for tq = 2 ln(255 o), up to the float
    rounding margin (far below a pixel for well-conditioned conics)."""
    _acc, _dn, _alpha, radii, _m2d, rec, _offsets, _ids = forward(elongated_scene(2))
    r = rec.double()[radii > 0]
    a, b, c, o, ex, ey = r[:, 2], r[:, 3], r[:, 4], r[:, 5], r[:, 7], r[:, 8]
    det = a * c - b * b
    well = ((a + c) ** 2 / det < 50) & (o > 2 / 255)
    assert int(well.sum()) > 50
    tq = 2 * torch.log(o * 255)
    assert (ex[well] >= torch.sqrt(tq * c / det)[well]).all() and (ey[well] >= torch.sqrt(tq * a / det)[well]).all()
    # the margins: 0.01 in q, and a relative 1e-5 (a + c)^2 / det (at most 5e-4 here)
    tight_x, tight_y = torch.sqrt((tq + 0.01) * c / det), torch.sqrt((tq + 0.01) * a / det)
    assert (ex[well] <= tight_x[well] * 1.0003 + 1e-4).all(), float((ex - tight_x)[well].max())
    assert (ey[well] <= tight_y[well] * 1.0003 + 1e-4).all(), float((ey - tight_y)[well].max())
    assert math.isfinite(float(ex.max()))


@pytest.mark.parametrize("seed", [0, 1])
def test_tile_lists_hold_only_tiles_the_alpha_ellipse_reaches(seed):
    """A Gaussian whose rect spans several tiles is listed only in tiles holding a pixel
    centre inside its alpha ellipse {q <= T} (T: the extent's threshold with its margins,
    from the record as stored; brute force in float64): the thin tilted ones leave out
    tiles of their bounding box, and the rendered pixels are the brute-force ones (above)."""
    _acc, _dn, _alpha, radii, _m2d, rec, offsets, ids = forward(elongated_scene(seed))
    r = rec.double()
    listed: dict[int, list[int]] = {}
    for t in range(TILES_X * TILES_Y):
        for i in ids[offsets[t]:offsets[t + 1]].tolist():
            listed.setdefault(i, []).append(t)
    pairs_in_rects = 0
    for i, tiles in listed.items():
        mx, my, a, b, c = (float(v) for v in r[i, :5])
        det = a * c - b * b
        T = max(0.0, (-2.0 * (float(r[i, 9]) + 0.01) + 0.01) * (1.0 + 1e-5 * (a + c) ** 2 / det))
        ex, ey = float(r[i, 7]), float(r[i, 8])
        r3 = float(radii[i])  # the rect: the 3-sigma radius's tiles narrowed to the extent's
        tx0 = max(0, math.floor((mx - r3) / TILE), math.floor((mx - ex - 0.5) / TILE))
        tx1 = min(TILES_X, math.ceil((mx + r3) / TILE), math.floor((mx + ex - 0.5) / TILE) + 1)
        ty0 = max(0, math.floor((my - r3) / TILE), math.floor((my - ey - 0.5) / TILE))
        ty1 = min(TILES_Y, math.ceil((my + r3) / TILE), math.floor((my + ey - 0.5) / TILE) + 1)
        pairs_in_rects += max(0, tx1 - tx0) * max(0, ty1 - ty0)
        if len(tiles) == 1 and (tx1 - tx0) * (ty1 - ty0) <= 1:
            continue
        for t in tiles:
            x0, y0 = (t % TILES_X) * TILE, (t // TILES_X) * TILE
            xs = torch.arange(x0, min(x0 + TILE, W), dtype=torch.float64) + 0.5 - mx
            ys = torch.arange(y0, min(y0 + TILE, H), dtype=torch.float64) + 0.5 - my
            dy, dx = torch.meshgrid(ys, xs, indexing="ij")
            q = a * dx * dx + 2 * b * dx * dy + c * dy * dy
            assert float(q.min()) <= T * (1 + 1e-9), f"Gaussian {i} listed in tile {t}, which its ellipse misses"
    assert len(ids) < 0.9 * pairs_in_rects  # the thin tilted ones skip tiles of their bounding boxes
