"""Body fitter: one pedestrian track's poses from LiDAR points, 2D keypoints and priors.

Fits the body template's pose at every frame of a track at once (all cameras, all
frames), in the world frame:

    joints/vertices(t) = R(t) s LBS(theta(t), template) + c(t)
    R(t) = R_box(t) BODY_TO_BOX exp(d_orient(t)),  c(t) = box centre(t) + d_centre(t)
    theta(t) = gait(phase(t); amplitudes) exp(d_pose(t))         (per joint)
    phase(t) = phase0 + 2 pi dist(t) / cycle

``dist(t)`` is the distance the box has travelled, so leg phase follows root speed (the
walking-gait prior of :mod:`omnire_body.gait`); ``s`` scales the template to the box
height. Free: phase0, cycle, the six gait amplitudes (per track) and per frame d_orient
(3), d_centre (3) and d_pose (23 x 3).

Energy (robust terms are Geman-McClure, ``r^2 / (r^2 + sigma^2)``):

- LiDAR: every point inside the (slightly enlarged) box, minus the ground slice, should lie
  on the body: robust distance to the nearest of a fixed subsample of posed vertices;
- keypoints: every 2D keypoint of an image estimator (any camera) should be where the
  matching joint projects: robust pixel error over the box height in that image, weighted
  by the keypoint confidence;
- priors: d_pose, d_orient, d_centre small (per-joint scales: knees and elbows bend about
  one axis, wrists, hands, head and spine barely move); second differences over time small
  (smooth joint angles); amplitudes near the gait shape's means.

Non-convex in the phase, the heading (front/back) and the cycle: a grid over them is scored
with the data terms first, and the best start is refined with Adam. A per-frame
confidence in [0, 1) grows with the evidence of that frame (LiDAR points, keypoint
confidence).
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from omnire.api import axis_angle_to_rotmat
from omnire_body.gait import GaitShape, default_amplitudes, gait_rotations, stride_weight
from omnire_body.rest import BODY_TO_BOX, neutral_body_pose

# Prior scale (radians) of the per-frame residual of each body joint (SMPL joints 1..23),
# per axis (x = flexion for the hinge joints).
_LOOSE, _FIRM, _HINGE_OFF = 0.35, 0.08, 0.04
_JOINT_SIGMA = np.full((23, 3), _FIRM)
for _j in (1, 2, 16, 17):  # hips and shoulders: ball joints
    _JOINT_SIGMA[_j - 1] = _LOOSE
for _j in (4, 5, 18, 19):  # knees, elbows: hinges (elbow axis conjugated; keep it loose-ish)
    _JOINT_SIGMA[_j - 1] = (_LOOSE, _HINGE_OFF, _HINGE_OFF) if _j in (4, 5) else (0.25, 0.15, 0.15)
for _j in (7, 8):  # ankles
    _JOINT_SIGMA[_j - 1] = (0.2, 0.08, 0.08)
for _j in (13, 14):  # collars
    _JOINT_SIGMA[_j - 1] = 0.1


@dataclasses.dataclass
class FitConfig:
    """Weights and budgets of the fitter."""

    iterations: int = 100
    """Adam iterations after the grid search."""
    lr: float = 0.04
    """Adam learning rate."""
    surface_points: int = 700
    """Template vertices the LiDAR term measures distances to (fixed subsample)."""
    lidar_sigma: float = 0.04
    """Robust scale (m) of point-to-body distances."""
    lidar_weight: float = 1.0
    """Weight of the LiDAR term (per point, averaged per frame and summed over frames)."""
    keypoint_sigma: float = 0.06
    """Robust scale of keypoint errors, in box heights."""
    keypoint_weight: float = 1.0
    """Weight of the keypoint term (per confident keypoint, averaged per observation)."""
    source_keypoint_weights: dict = dataclasses.field(default_factory=lambda: {"mediapipe": 0.1})
    """Factor on ``keypoint_weight`` per image estimator (keypoint observation source; 1 for
    the others): how far its keypoints are trusted against the LiDAR and the priors.
    MediaPipe 0.1, from ``omnire bench humanpose`` on the synthetic crowd (fusion MPJPE
    7.0 / 6.2 / 4.6 / 4.4 cm at 1 / 0.3 / 0.1 / 0; its keypoints, 0.04 box heights median
    error, systematically disagree with the template's joints: on frames they alone
    observe the fit is better without them)."""
    pose_prior_weight: float = 0.02
    """Weight of the per-frame residual priors (divided by their per-joint scales squared)."""
    smooth_weight: float = 2.0
    """Weight of the second differences over time (per frame, in rad^2 or m^2)."""
    centre_sigma: float = 0.08
    """Prior scale (m) of the body centre's offset from the box centre."""
    orient_sigma: float = 0.2
    """Prior scale (rad) of the heading/tilt residual."""
    amplitude_sigma: float = 0.25
    """Prior scale of the gait amplitudes relative to their means (fraction)."""
    phase_grid: int = 12
    """Phase offsets tried in the grid search."""
    cycle_grid: tuple[float, ...] = (0.7, 0.8, 0.9)
    """Cycle lengths tried, in body heights."""
    ground_slice: float = 0.06
    """Points lower than this (m) above the box bottom are ground, not body."""
    box_margin: float = 0.15
    """Points within this margin (m) around the box count (boxes are annotated tightly)."""
    min_points: int = 3
    """A frame is observed by LiDAR from this many body points on."""
    min_keypoints: float = 3.0
    """A frame is observed by an image estimator from this much keypoint confidence (sum) on."""
    shape: GaitShape = dataclasses.field(default_factory=GaitShape)
    """Gait prior means."""


@dataclasses.dataclass
class KeypointObservation:
    """2D keypoints of one track in one image.

    Attributes:
        frame: frame index; camera: camera index; source: estimator name.
        K: (3, 3) intrinsics and w2c: (4, 4) world-to-camera of that image.
        uv: (24, 2) keypoint pixels in SMPL joint order; conf: (24,) in [0, 1] (0 = none).
        box_height: height (px) of the pedestrian's projected box in that image.
    """

    frame: int
    camera: int
    K: np.ndarray
    w2c: np.ndarray
    uv: np.ndarray
    conf: np.ndarray
    box_height: float
    source: str = "keypoints"


@dataclasses.dataclass
class TrackData:
    """What the fitter sees of one track (F frames).

    Attributes:
        poses: (F, 4, 4) box-to-world (x heading, z up); size (3,) l, w, h; present (F,).
        points: F arrays (N_f, 3) of world LiDAR points in the box (ground removed), or None.
        keypoints: keypoint observations (any frames and cameras).
    """

    poses: np.ndarray
    size: np.ndarray
    present: np.ndarray
    points: list
    keypoints: list[KeypointObservation]

    def lidar_counts(self) -> np.ndarray:
        return np.array([0 if p is None else len(p) for p in self.points])

    def keypoint_evidence(self) -> np.ndarray:
        """(F,) summed keypoint confidence per frame (all cameras)."""
        out = np.zeros(len(self.present))
        for o in self.keypoints:
            out[o.frame] += float(o.conf.sum())
        return out


@dataclasses.dataclass
class FitResult:
    """Fitted poses of a track.

    Attributes:
        global_orient: (F, 3, 3) body-to-world; body_pose: (F, 23, 3, 3).
        centre: (F, 3) world position of the body's vertical centre.
        confidence: (F,) in [0, 1): evidence of each frame (0 where nothing observed it).
        lidar_frames, keypoint_frames: (F,) bool, frames observed by each kind of data.
        phase: (F,) gait phase; cycle (m); amplitudes (6,); loss: final energy.
    """

    global_orient: np.ndarray
    body_pose: np.ndarray
    centre: np.ndarray
    confidence: np.ndarray
    lidar_frames: np.ndarray
    keypoint_frames: np.ndarray
    phase: np.ndarray
    cycle: float
    amplitudes: np.ndarray
    loss: float


def points_for_fit(points: Optional[np.ndarray], pose: np.ndarray, size: np.ndarray, margin: float,
                   ground_slice: float) -> Optional[np.ndarray]:
    """World points (N, 3) inside the box enlarged by ``margin`` (not below its bottom), minus
    the ground slice; None when ``points`` is None."""
    if points is None:
        return None
    local = (points - pose[:3, 3]) @ pose[:3, :3]
    half = np.asarray(size) / 2
    keep = (np.abs(local[:, 0]) <= half[0] + margin) & (np.abs(local[:, 1]) <= half[1] + margin) \
        & (local[:, 2] <= half[2] + margin) & (local[:, 2] >= -half[2] + ground_slice)
    return np.asarray(points[keep], dtype=np.float64)


def travelled(poses: np.ndarray, present: np.ndarray, fps_times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative distance (F,) along the box path (smoothed over 5 frames, held across
    absent frames) and speed (F,) in m/s."""
    F = len(present)
    xy = poses[:, :2, 3].copy()
    idx = np.flatnonzero(present)
    if len(idx) == 0:
        return np.zeros(F), np.zeros(F)
    near = idx[np.abs(np.arange(F)[:, None] - idx[None]).argmin(1)]
    xy = xy[near]
    k = np.ones(5) / 5
    pad = np.pad(xy, ((2, 2), (0, 0)), mode="edge")
    smooth = np.stack([np.convolve(pad[:, i], k, mode="valid") for i in range(2)], 1)
    step = np.linalg.norm(np.diff(smooth, axis=0), axis=1)
    dist = np.concatenate([[0.0], np.cumsum(step)])
    dt = np.diff(fps_times) if len(fps_times) > 1 else np.array([0.1])
    speed = np.concatenate([[step[0] if len(step) else 0.0], step]) / np.concatenate([[dt[0]], dt]).clip(1e-3)
    speed = np.convolve(np.pad(speed, 2, mode="edge"), k, mode="valid")
    return dist, speed


class BodyFitter:
    """Fits tracks against one body template (see the module docstring)."""

    def __init__(self, joints: np.ndarray, parents: np.ndarray, vertices: np.ndarray, weights: np.ndarray,
                 config: Optional[FitConfig] = None, seed: int = 0) -> None:
        """joints (24, 3), parents (24,), vertices (V, 3), weights (V, 24): the template in
        SMPL's canonical frame."""
        self.config = config or FitConfig()
        self.parents = [int(p) for p in parents]
        rng = np.random.default_rng(seed)
        n = min(self.config.surface_points, len(vertices))
        sel = np.sort(rng.choice(len(vertices), n, replace=False))
        lo, hi = vertices[:, 1].min(), vertices[:, 1].max()
        self.height = float(hi - lo)
        self.centre_y = float((lo + hi) / 2)  # body's vertical centre (placed at the box centre)
        self.joints = torch.as_tensor(joints, dtype=torch.float32)
        self.verts = torch.as_tensor(vertices[sel], dtype=torch.float32)
        self.skin = torch.as_tensor(weights[sel], dtype=torch.float32)  # (n, 24) dense: one matmul blends
        self.neutral = torch.as_tensor(neutral_body_pose(joints), dtype=torch.float32)
        self.joint_sigma = torch.as_tensor(_JOINT_SIGMA, dtype=torch.float32)

    @classmethod
    def from_template(cls, template, config: Optional[FitConfig] = None) -> "BodyFitter":
        return cls(template.joints, template.parents, template.vertices, template.weights, config)

    # ------------------------------------------------------------------ model
    def _fk(self, rots: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """rots (B, 24, 3, 3) -> world rotations (B, 24, 3, 3), joint positions (B, 24, 3)
        of the unscaled template (pelvis rotation about the pelvis joint)."""
        J = self.joints
        Rw, tw = [rots[:, 0]], [J[0].expand(rots.shape[0], 3)]
        for j in range(1, 24):
            p = self.parents[j]
            Rw.append(Rw[p] @ rots[:, j])
            tw.append(tw[p] + (Rw[p] @ (J[j] - J[p]))[..., :])
        return torch.stack(Rw, 1), torch.stack(tw, 1)

    def _pose_model(self, rots: torch.Tensor, scale: float, centre: torch.Tensor, with_verts: bool
                    ) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """World joints (B, 24, 3) and subsampled vertices (B, n, 3) of bodies with full
        rotations ``rots`` (B, 24, 3, 3) (root = body-to-world) centred at ``centre`` (B, 3)."""
        Rw, tw = self._fk(rots)
        origin = torch.tensor([0.0, self.centre_y, 0.0])
        # world = R0 s (x - c) + centre, with R0 already inside Rw (root rotation applied about J0)
        J0 = self.joints[0]
        shift = centre - scale * (rots[:, 0] @ (origin - J0)) - scale * J0.expand_as(centre)

        def place(x: torch.Tensor) -> torch.Tensor:  # x: unscaled posed points about J0's rotation
            return scale * x + shift[:, None]

        joints = place(tw)
        if not with_verts:
            return joints, None
        A_t = tw - (Rw @ self.joints[None, :, :, None])[..., 0]  # (B, 24, 3)
        A = torch.cat([Rw, A_t[..., None]], -1).reshape(-1, 24, 12)  # skinning transforms
        Av = (self.skin @ A).reshape(-1, self.skin.shape[0], 3, 4)  # (B, n, 3, 4) blended per vertex
        v = (Av[..., :3] @ self.verts[None, :, :, None])[..., 0] + Av[..., 3]
        return joints, place(v)

    # ------------------------------------------------------------------ fitting
    def fit(self, data: TrackData, times: np.ndarray) -> FitResult:
        """Fit every present frame of ``data`` (``times`` (F,) seconds)."""
        cfg = self.config
        F = len(data.present)
        present = np.asarray(data.present, bool)
        box_R = torch.as_tensor(data.poses[:, :3, :3], dtype=torch.float32)
        box_t = torch.as_tensor(data.poses[:, :3, 3], dtype=torch.float32)
        scale = float(np.clip(data.size[2] / self.height, 0.8, 1.2))
        dist, speed = travelled(data.poses, present, np.asarray(times, dtype=np.float64))
        w_stride = torch.as_tensor(stride_weight(speed, cfg.shape), dtype=torch.float32)
        dist_t = torch.as_tensor(dist, dtype=torch.float32)
        height = scale * self.height

        counts = data.lidar_counts()
        kp_ev = data.keypoint_evidence()
        lidar_frames = present & (counts >= cfg.min_points)
        kp_frames = present & (kp_ev >= cfg.min_keypoints)
        pts = self._pad_points(data.points, lidar_frames)
        kps = self._stack_keypoints([o for o in data.keypoints if present[o.frame]])

        b2b = torch.as_tensor(BODY_TO_BOX, dtype=torch.float32)
        amps0 = torch.as_tensor(default_amplitudes(cfg.shape), dtype=torch.float32)

        def rotations(frames, phase0, cycle, amps, yaw, d_orient, d_pose):
            phase = phase0 + 2 * np.pi * dist_t[frames] / cycle
            body = gait_rotations(phase, w_stride[frames], amps, self.neutral)
            if d_pose is not None:
                body = body @ axis_angle_to_rotmat(d_pose)
            yaw_R = axis_angle_to_rotmat(torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], -1))
            go = box_R[frames] @ b2b @ yaw_R  # yaw about the body's up axis
            if d_orient is not None:
                go = go @ axis_angle_to_rotmat(d_orient)
            return torch.cat([go[:, None], body], 1), phase

        # ---- grid search over heading (front/back, and sideways when standing), phase, cycle
        obs_frames = np.flatnonzero(lidar_frames | kp_frames)
        walking = float(w_stride[torch.as_tensor(present)].mean()) > 0.3 if present.any() else False
        yaws = (0.0, np.pi) if walking else (0.0, np.pi / 2, np.pi, -np.pi / 2)
        phases = np.linspace(0, 2 * np.pi, cfg.phase_grid, endpoint=False) if walking else (0.0,)
        cycles = cfg.cycle_grid if walking else (cfg.shape.cycle_per_height,)
        best = (np.inf, 0.0, 0.0, cfg.shape.cycle_per_height * height)
        if len(obs_frames):
            sub = obs_frames if len(obs_frames) <= 24 else obs_frames[np.linspace(0, len(obs_frames) - 1, 24).astype(int)]
            fr = torch.as_tensor(sub)
            with torch.no_grad():
                for yaw in yaws:
                    for cyc in cycles:
                        for ph in phases:
                            rots, _ = rotations(fr, torch.tensor(float(ph)), torch.tensor(cyc * height), amps0,
                                                torch.full((len(sub),), float(yaw)), None, None)
                            e = self._data_energy(rots, box_t[fr], scale, sub, pts, kps)
                            if float(e) < best[0]:
                                best = (float(e), float(yaw), float(ph), cyc * height)

        # ---- joint refinement of everything
        frames = torch.arange(F)
        phase0 = torch.tensor(best[2], requires_grad=True)
        log_cycle = torch.tensor(float(np.log(best[3])), requires_grad=True)
        log_amps = torch.zeros(6, requires_grad=True)
        d_pose = torch.zeros(F, 23, 3, requires_grad=True)
        d_orient = torch.zeros(F, 3, requires_grad=True)
        d_centre = torch.zeros(F, 3, requires_grad=True)
        yaw = torch.full((F,), best[1])
        params = [phase0, log_cycle, log_amps, d_pose, d_orient, d_centre]
        opt = torch.optim.Adam(params, lr=cfg.lr, foreach=False)
        pres = torch.as_tensor(present)
        all_obs = np.flatnonzero(present)
        loss_val = float("nan")
        iters = cfg.iterations if len(obs_frames) else 0
        cyc_lo, cyc_hi = np.log(0.55 * height), np.log(1.1 * height)
        for it in range(iters):
            opt.zero_grad()
            cycle = torch.exp(log_cycle.clamp(cyc_lo, cyc_hi))
            amps = amps0 * torch.exp(log_amps)
            rots, _ = rotations(frames, phase0, cycle, amps, yaw, d_orient, d_pose)
            centre = box_t + d_centre
            e = self._data_energy(rots[all_obs], centre[all_obs], scale, all_obs, pts, kps)
            prior = (d_pose / self.joint_sigma).pow(2).sum((1, 2))[pres].sum() * cfg.pose_prior_weight
            prior = prior + ((d_orient / cfg.orient_sigma).pow(2).sum(1)[pres].sum()
                             + (d_centre / cfg.centre_sigma).pow(2).sum(1)[pres].sum()) * cfg.pose_prior_weight
            prior = prior + (log_amps / cfg.amplitude_sigma).pow(2).sum()
            smooth = self._smoothness(d_pose, pres) + self._smoothness(d_orient, pres) \
                + self._smoothness(d_centre, pres) * 10.0
            loss = e + prior + cfg.smooth_weight * smooth
            loss.backward()
            opt.step()
            loss_val = float(loss.detach())
        with torch.no_grad():
            cycle = torch.exp(log_cycle.clamp(cyc_lo, cyc_hi))
            amps = amps0 * torch.exp(log_amps)
            rots, phase = rotations(frames, phase0, cycle, amps, yaw, d_orient, d_pose)
            centre = box_t + d_centre
        evidence = counts * lidar_frames / 30.0 + kp_ev * kp_frames / 8.0
        return FitResult(
            global_orient=rots[:, 0].double().numpy(), body_pose=rots[:, 1:].double().numpy(),
            centre=centre.double().numpy(), confidence=evidence / (1.0 + evidence),
            lidar_frames=lidar_frames, keypoint_frames=kp_frames, phase=phase.double().numpy(),
            cycle=float(cycle), amplitudes=amps.double().numpy(), loss=loss_val)

    # ------------------------------------------------------------------ terms
    @staticmethod
    def _smoothness(x: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """Sum of squared second differences over runs of present frames; x (F, ...)."""
        if x.shape[0] < 3:
            return x.sum() * 0
        d2 = x[2:] - 2 * x[1:-1] + x[:-2]
        ok = present[2:] & present[1:-1] & present[:-2]
        return d2.pow(2).reshape(d2.shape[0], -1).sum(1)[ok].sum()

    @staticmethod
    def _pad_points(points: list, frames: np.ndarray) -> dict:
        """Frames with points -> (frame index (M,), padded points (M, N, 3), mask (M, N))."""
        idx = np.flatnonzero(frames)
        if len(idx) == 0:
            return {"frames": idx, "pts": torch.zeros(0, 1, 3), "mask": torch.zeros(0, 1, dtype=torch.bool)}
        N = max(len(points[f]) for f in idx)
        P = torch.zeros(len(idx), N, 3)
        M = torch.zeros(len(idx), N, dtype=torch.bool)
        for k, f in enumerate(idx):
            n = len(points[f])
            P[k, :n] = torch.as_tensor(points[f], dtype=torch.float32)
            M[k, :n] = True
        return {"frames": idx, "pts": P, "mask": M}

    def _stack_keypoints(self, obs: list[KeypointObservation]) -> dict:
        if not obs:
            return {"frames": np.zeros(0, int)}
        return {
            "frames": np.array([o.frame for o in obs]),
            "K": torch.as_tensor(np.stack([o.K for o in obs]), dtype=torch.float32),
            "w2c": torch.as_tensor(np.stack([o.w2c for o in obs]), dtype=torch.float32),
            "uv": torch.as_tensor(np.stack([o.uv for o in obs]), dtype=torch.float32),
            "conf": torch.as_tensor(np.stack([o.conf for o in obs]), dtype=torch.float32),
            "h": torch.as_tensor([max(o.box_height, 1.0) for o in obs], dtype=torch.float32),
            "w": torch.as_tensor([self.config.source_keypoint_weights.get(o.source, 1.0) for o in obs],
                                 dtype=torch.float32),
        }

    def _data_energy(self, rots: torch.Tensor, centre: torch.Tensor, scale: float, frames: np.ndarray,
                     pts: dict, kps: dict) -> torch.Tensor:
        """LiDAR + keypoint energy of bodies ``rots`` (B, 24, 3, 3) centred at ``centre``
        (B, 3) at ``frames`` (B,)."""
        cfg = self.config
        slot = {int(f): i for i, f in enumerate(frames)}
        lid = [slot.get(int(f), -1) for f in pts["frames"]]
        lid_rows = [k for k, s in enumerate(lid) if s >= 0]
        kp_rows = [k for k, f in enumerate(kps["frames"]) if int(f) in slot]
        need_v = bool(lid_rows)
        joints, verts = self._pose_model(rots, scale, centre, need_v)
        e = rots.sum() * 0
        if lid_rows:
            s_idx = torch.as_tensor([lid[k] for k in lid_rows])
            P, M = pts["pts"][lid_rows], pts["mask"][lid_rows]
            d2 = torch.cdist(P, verts[s_idx]).pow(2).min(2).values  # (m, N)
            rho = d2 / (d2 + cfg.lidar_sigma ** 2)
            per_frame = (rho * M).sum(1) / M.sum(1).clamp(min=1)
            # frames with more points count more, saturating (a frame is one observation)
            wf = M.sum(1).float().clamp(max=40) / 10.0
            e = e + cfg.lidar_weight * (per_frame * wf).sum()
        if kp_rows:
            s_idx = torch.as_tensor([slot[int(kps["frames"][k])] for k in kp_rows])
            J = joints[s_idx]  # (m, 24, 3)
            w2c = kps["w2c"][kp_rows]
            pc = (w2c[:, None, :3, :3] @ J[..., None])[..., 0] + w2c[:, None, :3, 3]
            z = pc[..., 2:].clamp(min=0.1)
            K = kps["K"][kp_rows]
            uv = (pc[..., :2] / z) * torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None] + K[:, None, :2, 2]
            r2 = ((uv - kps["uv"][kp_rows]) / kps["h"][kp_rows][:, None, None]).pow(2).sum(-1)
            rho = r2 / (r2 + cfg.keypoint_sigma ** 2)
            c = kps["conf"][kp_rows]
            per_obs = (rho * c).sum(1) / c.sum(1).clamp(min=1e-6) * c.sum(1).clamp(max=8) / 4
            e = e + cfg.keypoint_weight * (kps["w"][kp_rows] * per_obs).sum()
        return e
