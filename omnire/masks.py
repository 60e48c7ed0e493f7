"""Per-view masks: dynamic actors (human / vehicle) and sky.

Both prefer masks the dataset provides (``CameraSequence.dynamic_mask_paths`` /
``sky_mask_paths``) and otherwise derive them without any network weights:

- dynamic masks: the 3D boxes of the actors present at the frame, projected (convex hull of
  the 8 corners, clipped at the near plane) and z-buffered: a pixel belongs to the box its
  ray enters first, so a pedestrian behind a parked car is masked only where it is seen
  (PandaSet 002's pedestrians are mostly behind parked cars). Occluders without a box (a
  hedge, a wall, a pole) are found with the frame's LiDAR: box pixels near a return that
  lies in front of the box belong to no actor. Coarse (boxes include some background) but
  exact in where the actor is; where the LiDAR has no return on a box's pixels, the box
  stands;
- sky masks: pixels looking above the horizon and above the top-most LiDAR return of their
  image column (LiDAR of the frame and its neighbours, columns smoothed), as the sky returns
  nothing. Limits: buildings above the LiDAR's vertical field of view (+15 deg for
  PandaSet's Pandar64) or beyond its range are taken for sky; overhanging trees and wires
  are not resolved. So beside the mask, where its "sky" is not to be trusted: columns whose
  LiDAR returns reach the sensor's upper limit (what is seen there may go on above it), and
  textured pixels (trees, wires, skyline edges: the open sky is smooth). The mask drives only
  the opacity loss (weight 0.05), which skips the untrusted pixels.

Masks are cached per view as (H, W, 1) float tensors.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from omnire.data.images import ImageCache
from omnire.data.scene import SceneData, View
from omnire.lidar import LidarDepthTargets, near_upper_limit, project_to_pixels

HUMAN_CATEGORIES = frozenset({"human", "cyclist"})
"""Categories counted as humans in the human-region metrics (riders are people too)."""
VEHICLE_CATEGORIES = frozenset({"vehicle"})

_EDGES = [(0, 1), (0, 2), (0, 4), (1, 3), (1, 5), (2, 3), (2, 6), (3, 7), (4, 5), (4, 6), (5, 7), (6, 7)]
_CORNERS = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])


def box_polygon(pose: np.ndarray, size: np.ndarray, w2c: np.ndarray, K: np.ndarray, near: float = 0.1) -> Optional[np.ndarray]:
    """Image points (M,2) whose convex hull is the box's silhouette, or None if the box is
    behind the camera. Edges crossing the near plane are clipped there."""
    world = (_CORNERS * size) @ pose[:3, :3].T + pose[:3, 3]
    cam = world @ w2c[:3, :3].T + w2c[:3, 3]
    front = cam[:, 2] > near
    if not front.any():
        return None
    pts = [cam[i] for i in range(8) if front[i]]
    for a, b in _EDGES:
        if front[a] != front[b]:
            s = (near - cam[a, 2]) / (cam[b, 2] - cam[a, 2])
            pts.append(cam[a] + s * (cam[b] - cam[a]))
    pts = np.array(pts)
    return pts[:, :2] / pts[:, 2:] @ K[:2, :2].T + K[:2, 2]


def box_entry_depth(pose: np.ndarray, size: np.ndarray, c2w: np.ndarray, K: np.ndarray, xs: np.ndarray,
                    ys: np.ndarray) -> np.ndarray:
    """Camera depth (z, m) at which the rays through pixel centres ``(xs, ys)`` (P,) (integer
    pixel indices) enter the box (0 when the camera is inside it); inf where a ray misses.
    Slab test in box coordinates on rays d = (x, y, 1) in camera axes, so the ray parameter
    is the camera depth."""
    d = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0], (ys + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(xs))], -1)
    d_box = d @ (c2w[:3, :3].T @ pose[:3, :3])  # camera ray -> world -> box axes
    o_box = (c2w[:3, 3] - pose[:3, 3]) @ pose[:3, :3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-size / 2 - o_box) / d_box
        t2 = (size / 2 - o_box) / d_box
    # A ray parallel to a slab gives nan (origin on its face) or +-inf: nan-aware reductions.
    t_in = np.nanmax(np.minimum(t1, t2), -1)
    t_out = np.nanmin(np.maximum(t1, t2), -1)
    hit = t_out >= np.maximum(t_in, 0.0)
    return np.where(hit, np.maximum(t_in, 0.0), np.inf)


def fill_convex(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rasterise the convex hull of (M,2) points: (H,W) bool, pixel centres at +0.5."""
    mask = np.zeros((height, width), dtype=bool)
    if len(points) < 3:
        return mask
    hull = _convex_hull(points)
    x0, y0 = np.clip(np.floor(points.min(0)).astype(int), 0, [width, height])
    x1, y1 = np.clip(np.ceil(points.max(0)).astype(int) + 1, 0, [width, height])
    if x1 <= x0 or y1 <= y0 or len(hull) < 3:
        return mask
    ys, xs = np.mgrid[y0:y1, x0:x1] + 0.5
    inside = np.ones(xs.shape, dtype=bool)
    for i in range(len(hull)):
        (ax, ay), (bx, by) = hull[i], hull[(i + 1) % len(hull)]
        inside &= (bx - ax) * (ys - ay) - (by - ay) * (xs - ax) >= 0
    mask[y0:y1, x0:x1] = inside
    return mask


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise (in image coordinates, y down: clockwise on screen) hull, monotone chain."""
    pts = sorted(map(tuple, points))
    if len(pts) <= 2:
        return np.array(pts)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


class DynamicMasks:
    """Human / vehicle masks per view: dataset masks when given, else projected boxes,
    z-buffered against each other and against the frame's LiDAR (see :meth:`_unoccluded`).

    Args:
        occlusion_margin: a LiDAR return this many metres in front of where a pixel's ray
            enters its box shows an occluder (boxes are tight; the sweep and the image are
            not taken at exactly the same moment).
        occlusion_radius: pixels take the verdict of the nearest return on the same box's
            pixels within this many pixels (per 480 px of image width).
        lidar: the views' projected LiDAR, when the caller already has it (the depth
            targets of :class:`~omnire.observations.Observations`); made here otherwise.
    """

    def __init__(self, scene: SceneData, images: ImageCache, device: torch.device, occlusion_margin: float = 0.5,
                 occlusion_radius: float = 6.0, lidar: Optional[LidarDepthTargets] = None) -> None:
        self.scene, self.images, self.device = scene, images, device
        self.lidar = lidar if lidar is not None else LidarDepthTargets(scene, torch.device("cpu"))
        self.occlusion_margin = occlusion_margin
        self.occlusion_radius = occlusion_radius
        self._cache: dict[tuple[View, str], torch.Tensor] = {}
        self._owner: dict[View, np.ndarray] = {}

    def get(self, view: View, kind: str) -> torch.Tensor:
        """(H, W, 1) float mask of ``kind`` in {"human", "vehicle", "all"}."""
        key = (view, kind)
        if key not in self._cache:
            self._cache[key] = self._build(view, kind)
        return self._cache[key]

    def _build(self, view: View, kind: str) -> torch.Tensor:
        cam = self.scene.cameras[view.camera]
        given = (cam.dynamic_mask_paths or {}).get(kind)
        if given is not None:
            return self.images.camera_mask(cam, given[view.frame]).to(self.device)
        cats = {"human": HUMAN_CATEGORIES, "vehicle": VEHICLE_CATEGORIES,
                "all": HUMAN_CATEGORIES | VEHICLE_CATEGORIES}[kind]
        owner = self._nearest_box(view)
        keep = np.array([tr.category in cats for tr in self.scene.tracks] + [False])  # index -1: no box
        return torch.from_numpy(keep[owner]).float()[..., None].to(self.device)

    def _nearest_box(self, view: View) -> np.ndarray:
        """(H, W) int: index into scene.tracks of the box each pixel's ray enters first
        (every present track takes part, whatever its category), -1 where there is none."""
        if view in self._owner:
            return self._owner[view]
        cam = self.scene.cameras[view.camera]
        f = view.frame
        c2w = cam.cam_to_world[f]
        w2c = np.linalg.inv(c2w)
        depth = np.full((cam.height, cam.width), np.inf)
        owner = np.full((cam.height, cam.width), -1, dtype=np.int64)
        for i, tr in enumerate(self.scene.tracks):
            if not tr.present[f]:
                continue
            poly = box_polygon(tr.poses[f], tr.size, w2c, cam.intrinsics)
            if poly is None:
                continue
            ys, xs = np.nonzero(fill_convex(poly, cam.width, cam.height))
            if len(xs) == 0:
                continue
            z = box_entry_depth(tr.poses[f], tr.size, c2w, cam.intrinsics, xs, ys)
            # Silhouette pixels whose centre ray just misses the box: keep them, behind any hit.
            z = np.where(np.isfinite(z), z, 1e12)
            nearer = z < depth[ys, xs]
            depth[ys[nearer], xs[nearer]] = z[nearer]
            owner[ys[nearer], xs[nearer]] = i
        owner = self._unoccluded(view, owner, depth)
        self._owner = {view: owner}  # views are built one kind after another: keep the last
        return owner

    def _unoccluded(self, view: View, owner: np.ndarray, entry: np.ndarray) -> np.ndarray:
        """``owner`` (H, W) with -1 where the frame's LiDAR shows an occluder without a box
        (a hedge, a wall, a pole) in front of the owning box. ``entry`` (H, W): camera depth
        at which each pixel's ray enters its box (>= 1e12 where the centre ray misses it).
        Each box pixel takes the verdict of the nearest LiDAR return that falls on the same
        box's pixels, within ``occlusion_radius``; pixels with none keep their box."""
        projected = self.lidar.get(view) if (owner >= 0).any() else None
        if projected is None:
            return owner
        from scipy.spatial import cKDTree

        W = self.scene.cameras[view.camera].width
        idx, z = projected[0].cpu().numpy(), projected[1].cpu().numpy().astype(np.float64)
        ys, xs = idx // W, idx % W
        box = owner[ys, xs]
        hits = (box >= 0) & (entry[ys, xs] < 1e11)
        ys, xs, z, box = ys[hits], xs[hits], z[hits], box[hits]
        occluding = z < entry[ys, xs] - self.occlusion_margin
        radius = self.occlusion_radius * max(1.0, W / 480)
        out = owner.copy()
        for i in np.unique(box[occluding]):
            on_box = box == i
            py, px = np.nonzero(owner == i)
            tree = cKDTree(np.stack([xs[on_box], ys[on_box]], 1))
            dist, nearest = tree.query(np.stack([px, py], 1), distance_upper_bound=radius)
            found = np.isfinite(dist)
            hidden = np.zeros(len(px), dtype=bool)
            hidden[found] = occluding[on_box][nearest[found]]
            out[py[hidden], px[hidden]] = -1
        return out


class SkyMasks:
    """Sky masks per view: dataset masks when given, else the LiDAR-column heuristic, and
    where that heuristic's "sky" is not trusted (:meth:`trusted`; see the module docstring).

    Args:
        neighbour_frames: LiDAR of this many frames before and after the view's frame counts.
        column_smoothing: a column's boundary is the highest return within this fraction of
            the image width (sparse LiDAR).
        ceiling_margin_deg: returns within this many degrees of the LiDAR's upper limit (the
            99.5th percentile of the elevations of returns more than 5 m away, seen from the
            sensor origin) count as reaching it.
        texture_threshold: mean absolute grey-level difference (central, over a window of
            7 px per 480 px of image width) above which a "sky" pixel is textured.
    """

    def __init__(self, scene: SceneData, images: ImageCache, device: torch.device, neighbour_frames: int = 2,
                 column_smoothing: float = 0.02, ceiling_margin_deg: float = 3.0,
                 texture_threshold: float = 0.03) -> None:
        self.scene, self.images, self.device = scene, images, device
        self.neighbour_frames = neighbour_frames
        self.column_smoothing = column_smoothing
        self.ceiling_margin_deg = ceiling_margin_deg
        self.texture_threshold = texture_threshold
        self._cache: dict[View, tuple[Optional[torch.Tensor], Optional[torch.Tensor]]] = {}

    def available(self) -> bool:
        return all(c.sky_mask_paths is not None for c in self.scene.cameras) or self.scene.lidar is not None

    def get(self, view: View) -> Optional[torch.Tensor]:
        """(H, W, 1) {0, 1}: 1 where sky; None without dataset masks or LiDAR."""
        return self._entry(view)[0]

    def trusted(self, view: View) -> Optional[torch.Tensor]:
        """(H, W, 1) {0, 1}: 0 where the mask says sky but the heuristic cannot tell; None
        when every pixel's label is trusted (masks given by the dataset)."""
        return self._entry(view)[1]

    def _entry(self, view: View) -> tuple[Optional[torch.Tensor], Optional[torch.Tensor]]:
        if view not in self._cache:
            self._cache[view] = self._build(view)
        return self._cache[view]

    def _build(self, view: View) -> tuple[Optional[torch.Tensor], Optional[torch.Tensor]]:
        cam = self.scene.cameras[view.camera]
        if cam.sky_mask_paths is not None:
            return self.images.camera_mask(cam, cam.sky_mask_paths[view.frame]).to(self.device), None
        if self.scene.lidar is None:
            return None, None
        f = view.frame
        lo, hi = max(0, f - self.neighbour_frames), min(self.scene.num_frames, f + self.neighbour_frames + 1)
        frames = [g for g in range(lo, hi) if self.scene.lidar.points[g] is not None]
        W, H = cam.width, cam.height
        c2w = cam.cam_to_world[f]
        # elevation of each pixel's ray in the world (z up)
        v, u = np.mgrid[0:H, 0:W] + 0.5
        rays = np.stack([(u - cam.intrinsics[0, 2]) / cam.intrinsics[0, 0],
                         (v - cam.intrinsics[1, 2]) / cam.intrinsics[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
        up = rays[..., 2] / np.linalg.norm(rays, axis=-1) > np.sin(np.deg2rad(1.0))
        top = np.full(W, H, dtype=np.int64)  # top-most LiDAR row per column (H = none)
        at_ceiling = np.zeros(W, dtype=bool)  # columns with a return at the LiDAR's upper limit
        if frames:
            points = np.concatenate([self.scene.lidar.points[g] for g in frames])
            cols, rows, _, kept = project_to_pixels(points, c2w, cam.intrinsics, W, H)
            np.minimum.at(top, cols, rows)
            high = near_upper_limit(self.scene.lidar, frames, self.ceiling_margin_deg)
            if high is not None:
                at_ceiling[cols[high[kept]]] = True
        r = max(1, int(self.column_smoothing * W))
        # a column's boundary is the highest return among its neighbours (sparse LiDAR)
        smoothed = -F.max_pool1d(-torch.from_numpy(top).float()[None, None], 2 * r + 1, stride=1, padding=r)[0, 0].numpy()
        sky = up & (v < smoothed[None, :])
        at_ceiling = F.max_pool1d(torch.from_numpy(at_ceiling).float()[None, None], 2 * r + 1, stride=1,
                                  padding=r)[0, 0].numpy() > 0
        textured = self._textured(self.images.camera_image(cam, f))
        trusted = ~(sky & (at_ceiling[None, :] | textured))
        as_mask = lambda m: torch.from_numpy(m).float()[..., None].to(self.device)
        return as_mask(sky), as_mask(trusted)

    def _textured(self, image: torch.Tensor) -> np.ndarray:
        """(H, W) bool: pixels near texture in (H, W, 3) ``image`` (window and spacing scale
        with the image width, so the threshold means the same at any resolution)."""
        H, W = image.shape[:2]
        s = max(1, round(W / 480))
        grey = image.float().mean(-1)[None, None]
        grad = torch.zeros_like(grey)
        grad[..., :, s:-s] += (grey[..., :, 2 * s:] - grey[..., :, :-2 * s]).abs()
        grad[..., s:-s, :] += (grey[..., 2 * s:, :] - grey[..., :-2 * s, :]).abs()
        k = 7 * s
        mean = F.avg_pool2d(grad, k, stride=1, padding=k // 2, count_include_pad=False)[..., :H, :W]
        grown = F.max_pool2d((mean > self.texture_threshold).float(), 5 * s, stride=1, padding=(5 * s) // 2)
        return grown[0, 0, :H, :W].numpy() > 0
