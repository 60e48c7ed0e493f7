"""Ground-truth mesh renderer (torch, CPU): z-buffer rasterisation (the LiDAR is ray-traced
in :mod:`omnire_synthetic.lidar`).

Nothing here touches the Gaussian rasterizer: the synthetic scenes are the truth that the
Gaussian methods are measured against.

Rasterisation (:func:`rasterize`): triangles are transformed to the OpenCV camera frame,
clipped against the near plane (0, 1 or 2 triangles each), projected, and expanded into
(pixel, triangle) pairs over each triangle's pixel bounding box, in chunks of about a
million pairs. Coverage uses screen-space edge functions; the z-buffer is one
``scatter_reduce(amin)`` over int64 keys ``depth_bits << 31 | face``, so the nearest face
per pixel wins without a Python loop. The winner's depth and barycentrics are then
recomputed exactly by intersecting the pixel ray with the original triangle
(Moller-Trumbore), so clipping never distorts attributes.

Conventions: pixel (i, j) has its centre at (i + 0.5, j + 0.5); K is the pinhole matrix
in that convention; depth is camera z (not range).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

PAIR_CHUNK = 1 << 20
_FACE_BITS = 31
_FACE_MASK = (1 << _FACE_BITS) - 1
_EMPTY = torch.iinfo(torch.int64).max


@dataclasses.dataclass
class Raster:
    """Per-pixel result. depth (H, W) float32 camera z (inf = nothing); face (H, W) int64
    (-1 = nothing); bary (H, W, 3) float32 barycentrics of the hit in ``face``."""

    depth: torch.Tensor
    face: torch.Tensor
    bary: torch.Tensor


def _clip_near(tri: torch.Tensor, ids: torch.Tensor, near: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Clip (N, 3, 3) camera-space triangles against z = near. Returns triangles wholly in
    front and the original face id of each."""
    behind = tri[..., 2] < near  # (N, 3)
    nb = behind.sum(1)
    out_t, out_i = [tri[nb == 0]], [ids[nb == 0]]
    ar = torch.arange(3)
    for n_behind in (1, 2):
        sel = nb == n_behind
        if not sel.any():
            continue
        t, i = tri[sel], ids[sel]
        # Roll so the odd vertex (the only behind one, or the only front one) comes first.
        odd = (behind[sel] if n_behind == 1 else ~behind[sel]).to(torch.int64).argmax(1)
        order = (odd[:, None] + ar[None]) % 3  # (n, 3)
        t = torch.gather(t, 1, order[..., None].expand(-1, -1, 3))
        a, b, c = t[:, 0], t[:, 1], t[:, 2]

        def cut(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
            s = (near - p[:, 2]) / (q[:, 2] - p[:, 2])
            return p + (q - p) * s[:, None]

        ab, ac = cut(a, b), cut(a, c)
        if n_behind == 1:  # a behind: quad (ab, b, c, ac) -> two triangles
            out_t += [torch.stack([ab, b, c], 1), torch.stack([ab, c, ac], 1)]
            out_i += [i, i]
        else:  # only a in front
            out_t.append(torch.stack([a, ab, ac], 1))
            out_i.append(i)
    return torch.cat(out_t), torch.cat(out_i)


def rasterize(
    v_cam: torch.Tensor,
    faces: torch.Tensor,
    K: np.ndarray,
    height: int,
    width: int,
    near: float = 0.05,
    face_subset: torch.Tensor | None = None,
) -> Raster:
    """Z-buffer rasterisation of a triangle mesh.

    Args:
        v_cam: (V, 3) float32 vertices in the OpenCV camera frame.
        faces: (F, 3) int64 vertex indices.
        K: (3, 3) intrinsics (pixel centres at +0.5).
        height, width: image size.
        near: near clipping distance in metres.
        face_subset: optional (S,) face indices to draw (others are ignored).
    """
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    ids = torch.arange(faces.shape[0]) if face_subset is None else face_subset
    tri = v_cam[faces[ids]]  # (N, 3, 3)
    z = tri[..., 2]
    keep = (z > near).any(1)
    # Cull triangles wholly outside one side of the frustum (only decidable in front).
    front = (z > near).all(1)
    zs = z.clamp(min=near)
    u = tri[..., 0] / zs * fx + cx
    v = tri[..., 1] / zs * fy + cy
    outside = ((u < 0).all(1) | (u > width).all(1) | (v < 0).all(1) | (v > height).all(1)) & front
    keep &= ~outside
    tri, ids = _clip_near(tri[keep], ids[keep], near)

    z = tri[..., 2]  # (N, 3), all >= near
    px = tri[..., 0] / z * fx + cx
    py = tri[..., 1] / z * fy + cy
    # Pixel-centre bounding boxes first: most faces of dense meshes (bodies) cover no pixel
    # centre at all, so everything after this runs on the survivors only.
    i0 = torch.ceil(px.min(1).values - 0.5).clamp(min=0)
    i1 = torch.floor(px.max(1).values - 0.5).clamp(max=width - 1)
    j0 = torch.ceil(py.min(1).values - 0.5).clamp(min=0)
    j1 = torch.floor(py.max(1).values - 0.5).clamp(max=height - 1)
    bw = (i1 - i0 + 1).clamp(min=0)
    bh = (j1 - j0 + 1).clamp(min=0)
    count = (bw * bh).to(torch.int64)
    sel = count > 0
    tri, ids, count, px, py = tri[sel], ids[sel], count[sel], px[sel], py[sel]
    i0, j0, bw = i0[sel].to(torch.int64), j0[sel].to(torch.int64), bw[sel].to(torch.int64)
    # Edge functions as linear forms in the sample position: l_k = A_k x + B_k y + C_k.
    x0, x1, x2 = px.unbind(1)
    y0, y1, y2 = py.unbind(1)
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    ok = area.abs() > 1e-9
    tri, ids, count, i0, j0, bw = tri[ok], ids[ok], count[ok], i0[ok], j0[ok], bw[ok]
    x0, x1, x2, y0, y1, y2, area = (t[ok] for t in (x0, x1, x2, y0, y1, y2, area))
    inv_a = 1.0 / area
    # l0 = ((x1-x)(y2-y) - (x2-x)(y1-y)) / area, l1 = ((x2-x)(y0-y) - (x0-x)(y2-y)) / area
    A0, B0, C0 = (y1 - y2) * inv_a, (x2 - x1) * inv_a, (x1 * y2 - x2 * y1) * inv_a
    A1, B1, C1 = (y2 - y0) * inv_a, (x0 - x2) * inv_a, (x2 * y0 - x0 * y2) * inv_a
    iz = 1.0 / tri[..., 2]  # (N, 3) inverse depth is affine in screen space
    Az = A0 * (iz[:, 0] - iz[:, 2]) + A1 * (iz[:, 1] - iz[:, 2])
    Bz = B0 * (iz[:, 0] - iz[:, 2]) + B1 * (iz[:, 1] - iz[:, 2])
    Cz = C0 * (iz[:, 0] - iz[:, 2]) + C1 * (iz[:, 1] - iz[:, 2]) + iz[:, 2]
    coef = torch.stack([A0, B0, C0, A1, B1, C1, Az, Bz, Cz], 1)  # (N, 9)

    zbuf = torch.full((height * width,), _EMPTY, dtype=torch.int64)
    ends = torch.cumsum(count, 0)
    n = count.shape[0]
    start_tri = 0
    eps = -1e-6
    while start_tri < n:
        base = int(ends[start_tri - 1]) if start_tri else 0
        stop = int(torch.searchsorted(ends, torch.tensor(base + PAIR_CHUNK), right=True))
        stop = max(stop, start_tri + 1)
        cnt = count[start_tri:stop]
        t_idx = torch.repeat_interleave(torch.arange(start_tri, stop), cnt)  # (P,)
        offs = torch.cumsum(cnt, 0) - cnt
        local = torch.arange(t_idx.shape[0]) - torch.repeat_interleave(offs, cnt)
        w = bw[t_idx]
        xi = i0[t_idx] + local % w
        yi = j0[t_idx] + torch.div(local, w, rounding_mode="floor")
        xs = xi.to(torch.float32) + 0.5
        ys = yi.to(torch.float32) + 0.5
        c = coef[t_idx]  # (P, 9)
        l0 = c[:, 0] * xs + c[:, 1] * ys + c[:, 2]
        l1 = c[:, 3] * xs + c[:, 4] * ys + c[:, 5]
        inside = (l0 >= eps) & (l1 >= eps) & (1.0 - l0 - l1 >= eps)
        izp = c[:, 6] * xs + c[:, 7] * ys + c[:, 8]
        inside &= izp > 0
        depth = (1.0 / izp[inside]).to(torch.float32)
        key = (depth.view(torch.int32).to(torch.int64) << _FACE_BITS) | ids[t_idx[inside]]
        pix = yi[inside] * width + xi[inside]
        zbuf.scatter_reduce_(0, pix, key, reduce="amin")
        start_tri = stop

    hit = zbuf != _EMPTY
    face = torch.where(hit, zbuf & _FACE_MASK, torch.full_like(zbuf, -1))
    depth = torch.full((height * width,), float("inf"))
    bary = torch.zeros(height * width, 3)
    if hit.any():
        pix = torch.nonzero(hit).squeeze(1)
        f = face[pix]
        xs = (pix % width).to(torch.float32) + 0.5
        ys = torch.div(pix, width, rounding_mode="floor").to(torch.float32) + 0.5
        d = torch.stack([(xs - cx) / fx, (ys - cy) / fy, torch.ones_like(xs)], 1)  # (P, 3) z = 1
        t, b = ray_triangle(torch.zeros_like(d), d, v_cam[faces[f]])
        # Grazing hits can fall a hair outside the triangle; they still won the z-test.
        b = b.clamp(min=0)
        b = b / b.sum(1, keepdim=True)
        depth[pix] = t.to(torch.float32)
        bary[pix] = b.to(torch.float32)
    return Raster(depth.view(height, width), face.view(height, width), bary.view(height, width, 3))


def ray_triangle(o: torch.Tensor, d: torch.Tensor, tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Moller-Trumbore for matched rays and triangles.

    Args: o, d: (..., 3) ray origins and directions; tri: (..., 3, 3) vertices.
    Returns: t (...,) ray parameter (NaN when parallel) and barycentrics (..., 3).
    """
    v0, v1, v2 = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    e1, e2 = v1 - v0, v2 - v0
    p = torch.linalg.cross(d, e2)
    det = (e1 * p).sum(-1)
    inv = torch.where(det.abs() > 1e-12, 1.0 / det, torch.full_like(det, float("nan")))
    s = o - v0
    u = (s * p).sum(-1) * inv
    q = torch.linalg.cross(s, e1)
    v = (d * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    return t, torch.stack([1.0 - u - v, u, v], -1)


def look_rotation(forward: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """(3, 3) OpenCV camera-to-frame rotation looking along ``forward`` (x right, y down)."""
    f = forward / np.linalg.norm(forward)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    down = np.cross(f, r)
    return np.stack([r, down, f], axis=1)


def sphere_in_frustum(centres_cam: np.ndarray, radii: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: spheres (centres in the OpenCV camera frame (N, 3), radii (N,)) that meet the
    view frustum (conservative: may keep a few that are just outside)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    planes = np.array([[fx, 0, cx], [-fx, 0, width - cx], [0, fy, cy], [0, -fy, height - cy], [0, 0, 1.0]])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)  # inward normals through the centre
    return ((centres_cam @ planes.T) >= -radii[:, None]).all(1)


def sample_texture(textures: torch.Tensor, material: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear, wrapping texture lookup.

    Args: textures (M, T, T, 3); material (P,) int64; uv (P, 2) in texture repeats.
    Returns: (P, 3) colours.
    """
    T = textures.shape[1]
    x = uv[:, 0] * T - 0.5
    y = uv[:, 1] * T - 0.5
    x0f, y0f = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0f)[:, None], (y - y0f)[:, None]
    x0 = x0f.to(torch.int64) % T
    y0 = y0f.to(torch.int64) % T
    x1, y1 = (x0 + 1) % T, (y0 + 1) % T
    flat = textures.reshape(-1, 3)
    base = material * T * T

    def at(yy: torch.Tensor, xx: torch.Tensor) -> torch.Tensor:
        return flat[base + yy * T + xx]

    return (at(y0, x0) * (1 - fx) * (1 - fy) + at(y0, x1) * fx * (1 - fy)
            + at(y1, x0) * (1 - fx) * fy + at(y1, x1) * fx * fy)
