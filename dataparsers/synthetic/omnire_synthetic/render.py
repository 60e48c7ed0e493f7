"""Ground-truth mesh renderer (torch, CPU): z-buffer rasterisation and LiDAR ray casting.

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

LiDAR (:func:`raycast_via_id_buffer`): the scene is rasterised into four 90-degree faces
around the sensor (only the rows the beam elevations need); each beam then tests the
triangles that won the 3x3 pixels around its direction with an exact ray-triangle
intersection and keeps the nearest hit. Points therefore lie exactly on the meshes. A beam
whose nearest candidate hit lies clearly behind the surface its own pixel shows (a
sub-pixel triangle was missed) is dropped, like a real LiDAR return lost at an edge.

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


@dataclasses.dataclass
class LidarPattern:
    """A spinning LiDAR: beam elevations (degrees) times azimuth steps."""

    elevations_deg: np.ndarray
    azimuth_step_deg: float

    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit directions (R, 3) in the sensor frame (x fwd, y left, z up) and beam ids (R,)."""
        az = np.deg2rad(np.arange(0.0, 360.0, self.azimuth_step_deg))
        el = np.deg2rad(self.elevations_deg)
        A, E = np.meshgrid(az, el, indexing="xy")  # (n_el, n_az)
        d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
        beam = np.repeat(np.arange(len(el)), len(az))
        return d, beam


def sphere_in_frustum(centres_cam: np.ndarray, radii: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: spheres (centres in the OpenCV camera frame (N, 3), radii (N,)) that meet the
    view frustum (conservative: may keep a few that are just outside)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    planes = np.array([[fx, 0, cx], [-fx, 0, width - cx], [0, fy, cy], [0, -fy, height - cy], [0, 0, 1.0]])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)  # inward normals through the centre
    return ((centres_cam @ planes.T) >= -radii[:, None]).all(1)


@dataclasses.dataclass
class CullGroups:
    """Optional culling for :func:`raycast_via_id_buffer`: faces always drawn, plus objects
    (bounding spheres in the sensor frame (N, 3), radii (N,), face indices of each)."""

    always: torch.Tensor
    centres: np.ndarray
    radii: np.ndarray
    faces_of: list[torch.Tensor]

    def subset(self, sensor_to_cam: np.ndarray, K: np.ndarray, width: int, height: int) -> torch.Tensor:
        vis = sphere_in_frustum(self.centres @ sensor_to_cam.T, self.radii, K, width, height)
        return torch.cat([self.always] + [self.faces_of[k] for k in np.flatnonzero(vis)])


def raycast_via_id_buffer(
    v_sensor: torch.Tensor,
    faces: torch.Tensor,
    dirs: np.ndarray,
    elev_range_deg: tuple[float, float],
    face_width: int = 256,
    near: float = 0.3,
    max_range: float = 120.0,
    cull: CullGroups | None = None,
    exact_groups: list[torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact first hits of rays from the sensor origin.

    Args:
        v_sensor: (V, 3) vertices in the sensor frame (x fwd, y left, z up).
        faces: (F, 3).
        dirs: (R, 3) unit ray directions in the sensor frame.
        elev_range_deg: (min, max) beam elevation, to size the rendered band.
        face_width: pixels across each 90-degree face.
        exact_groups: optional face-index sets (e.g. one per actor) tested in full for every
            ray whose 3x3 candidates include one of their faces. Body meshes have triangles
            far smaller than an ID-buffer pixel (6 mm edges against 6 cm at 10 m), so the
            candidates alone miss most of a person.
    Returns:
        range (R,) float32 (NaN = no return), face (R,) int64 (-1), barycentrics (R, 3).
    """
    f = face_width / 2.0
    lo, hi = np.deg2rad(elev_range_deg[0]), np.deg2rad(elev_range_deg[1])
    # On a face, image y = -tan(elevation) / cos(local azimuth); |local azimuth| <= 45 deg.
    yn_min, yn_max = -np.tan(hi) * np.sqrt(2.0), -np.tan(lo) * np.sqrt(2.0)
    margin = 3.0 / f
    yn_min, yn_max = min(yn_min, -np.tan(hi)) - margin, max(yn_max, -np.tan(lo)) + margin
    H = int(np.ceil((yn_max - yn_min) * f))
    K = np.array([[f, 0.0, f], [0.0, f, -yn_min * f], [0.0, 0.0, 1.0]])
    d = torch.as_tensor(dirs, dtype=torch.float32)
    az = torch.atan2(d[:, 1], d[:, 0])
    face_of_ray = torch.round(az / (np.pi / 2)).to(torch.int64) % 4
    R_n = d.shape[0]
    cand = torch.full((R_n, 9), -1, dtype=torch.int64)
    own_depth_range = torch.full((R_n,), float("inf"))
    for k in range(4):
        yaw = k * np.pi / 2
        Rk = look_rotation(np.array([np.cos(yaw), np.sin(yaw), 0.0]))  # cam -> sensor
        Rk_t = torch.as_tensor(Rk.T, dtype=torch.float32)
        subset = None if cull is None else cull.subset(Rk.T, K, face_width, H)
        r = rasterize(v_sensor @ Rk_t.T, faces, K, H, face_width, near=near, face_subset=subset)
        sel = torch.nonzero(face_of_ray == k).squeeze(1)
        dc = d[sel] @ Rk_t.T  # (n, 3) camera-frame directions
        u = dc[:, 0] / dc[:, 2] * f + f
        v = dc[:, 1] / dc[:, 2] * f + float(K[1, 2])
        ui, vi = torch.floor(u).to(torch.int64), torch.floor(v).to(torch.int64)
        n = 0
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                uu = (ui + du).clamp(0, face_width - 1)
                vv = (vi + dv).clamp(0, H - 1)
                cand[sel, n] = r.face[vv, uu]
                n += 1
        uu, vv = ui.clamp(0, face_width - 1), vi.clamp(0, H - 1)
        own_depth_range[sel] = r.depth[vv, uu] / dc[:, 2]  # z-depth -> range along this ray
    valid = cand >= 0
    tri = v_sensor[faces[cand.clamp(min=0)]]  # (R, 9, 3, 3)
    dd = d[:, None].expand(-1, 9, -1)
    t, b = ray_triangle(torch.zeros_like(dd), dd, tri)
    inside = valid & (b >= -1e-6).all(-1) & (t > near) & (t < max_range) & torch.isfinite(t)
    t = torch.where(inside, t, torch.full_like(t, float("inf")))
    best = t.argmin(1)
    rng = t.gather(1, best[:, None]).squeeze(1)
    face = cand.gather(1, best[:, None]).squeeze(1)
    bary = b[torch.arange(R_n), best]
    if exact_groups:
        rng, face, bary = _exact_group_hits(v_sensor, faces, d, cand, rng, face, bary, exact_groups, near, max_range)
    # A hit far behind what the ray's own pixel shows means a sub-pixel face was missed.
    missed = rng > own_depth_range * 1.05 + 0.3
    bad = ~torch.isfinite(rng) | missed
    rng = torch.where(bad, torch.full_like(rng, float("nan")), rng)
    face = torch.where(bad, torch.full_like(face, -1), face)
    return rng.to(torch.float32), face, bary.to(torch.float32)


def _exact_group_hits(v_sensor: torch.Tensor, faces: torch.Tensor, d: torch.Tensor, cand: torch.Tensor,
                      rng: torch.Tensor, face: torch.Tensor, bary: torch.Tensor, groups: list[torch.Tensor],
                      near: float, max_range: float, chunk: int = 1 << 21
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest hits (R,), faces (R,) and barycentrics (R, 3) after testing each group's faces
    in full for the rays (R, 3) whose candidates (R, 9) touch the group; nearer exact hits
    replace the candidates' ones. Pairs are pruned with a direction grid (see
    :func:`_ray_face_pairs`), so a ray meets only the faces around it."""
    owner = torch.full((faces.shape[0],), -1, dtype=torch.int64)
    for k, idx in enumerate(groups):
        owner[idx] = k
    cand_owner = torch.where(cand >= 0, owner[cand.clamp(min=0)], torch.full_like(cand, -1))
    rng, face, bary = rng.clone(), face.clone(), bary.clone()
    for k, idx in enumerate(groups):
        rays = torch.nonzero((cand_owner == k).any(1)).squeeze(1)
        if len(rays) == 0 or len(idx) == 0:
            continue
        tri = v_sensor[faces[idx]]  # (Fk, 3, 3)
        pr, pf = _ray_face_pairs(d[rays], tri)
        for s in range(0, len(pr), chunk):
            r, f = pr[s:s + chunk], pf[s:s + chunk]
            dd = d[rays[r]]
            t, b = ray_triangle(torch.zeros_like(dd), dd, tri[f])
            hit = (b >= -1e-6).all(-1) & (t > near) & (t < max_range) & torch.isfinite(t)
            t = torch.where(hit, t, torch.full_like(t, float("inf")))
            # nearest hit per ray: sort pairs by (ray, t) and keep each ray's first
            order = torch.argsort(r.to(torch.float64) * 1e6 + t.clamp(max=1e5).to(torch.float64))
            r_s, t_s, f_s, b_s = r[order], t[order], f[order], b[order]
            first = torch.ones_like(r_s, dtype=torch.bool)
            first[1:] = r_s[1:] != r_s[:-1]
            r_s, t_s, f_s, b_s = r_s[first], t_s[first], f_s[first], b_s[first]
            g = rays[r_s]
            better = t_s < rng[g]
            rng[g[better]] = t_s[better]
            face[g[better]] = idx[f_s[better]]
            bary[g[better]] = b_s[better]
    return rng, face, bary


def _ray_face_pairs(dirs: torch.Tensor, tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate (ray, face) pairs: a face can only contain a ray direction lying within the
    face's angular radius of its centroid direction, so faces are binned on a direction grid
    (azimuth/elevation about the rays' mean direction) with cells no smaller than the
    largest angular radius, and each ray meets the faces of its cell and the 8 around it.

    Args: dirs (n, 3) unit rays from the origin; tri (Fk, 3, 3) triangles.
    Returns: ray indices (P,) and face indices (P,).
    """
    n, Fk = dirs.shape[0], tri.shape[0]
    cen = tri.mean(1)
    cen_u = cen / cen.norm(dim=1, keepdim=True).clamp(min=1e-9)
    vert_u = tri / tri.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    radius = torch.arccos((vert_u * cen_u[:, None]).sum(-1).clamp(-1.0, 1.0)).max(1).values  # (Fk,)
    cell = max(float(radius.max()) * 1.01, np.deg2rad(0.1))
    mean = dirs.mean(0)
    if float(mean.norm()) < 0.5 or cell > np.deg2rad(10.0):  # wide groups: every pair
        return torch.arange(n).repeat_interleave(Fk), torch.arange(Fk).repeat(n)
    # frame with the rays' mean direction as +x: azimuth/elevation stay far from the wrap
    x = mean / mean.norm()
    helper = torch.tensor([0.0, 0.0, 1.0]) if abs(float(x[2])) < 0.9 else torch.tensor([0.0, 1.0, 0.0])
    y = torch.linalg.cross(helper, x)
    y = y / y.norm()
    z = torch.linalg.cross(x, y)
    R = torch.stack([x, y, z])  # rows: new axes

    def angles(u: torch.Tensor) -> torch.Tensor:
        v = u @ R.T
        return torch.stack([torch.atan2(v[:, 1], v[:, 0]), torch.asin(v[:, 2].clamp(-1.0, 1.0))], 1)

    fa = torch.floor(angles(cen_u) / cell).to(torch.int64)  # (Fk, 2)
    ra = torch.floor(angles(dirs) / cell).to(torch.int64)  # (n, 2)
    lo = torch.minimum(fa.min(0).values, ra.min(0).values) - 1
    span = int((torch.maximum(fa.max(0).values, ra.max(0).values) - lo).max()) + 2
    fkey = (fa[:, 0] - lo[0]) * span + (fa[:, 1] - lo[1])
    order = torch.argsort(fkey)
    sorted_keys = fkey[order]
    off = torch.tensor([(da, de) for da in (-1, 0, 1) for de in (-1, 0, 1)])
    q = ra[:, None] + off[None]  # (n, 9, 2)
    qkey = ((q[..., 0] - lo[0]) * span + (q[..., 1] - lo[1])).reshape(-1)
    start = torch.searchsorted(sorted_keys, qkey, side="left")
    count = torch.searchsorted(sorted_keys, qkey, side="right") - start
    ray_of = torch.arange(n).repeat_interleave(9).repeat_interleave(count)
    base = torch.repeat_interleave(start - torch.cumsum(count, 0) + count, count)
    pos = torch.arange(int(count.sum())) + base
    return ray_of, order[pos]


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
