"""SMPL actor node: pedestrians as Gaussians bound to a skinned body template.

World Gaussians of person i at frame t (OmniRe: world = T_h(t) (x) LBS(theta(t), G)):

    x_world = R_box(t) G_i(t) LBS(theta_i(t), x_canon) + t_box(t)

- ``x_canon``: Gaussian means in the person's canonical body frame (SMPL axes: x = body's
  left, y up, z forward; the template's rest pose), initialised on template vertices
  (area-weighted subsample). Each Gaussian carries the skinning weights of the vertex it
  was made from (buffers ``skin_joints`` / ``skin_weights``, K largest weights), so the
  core densification, generic over per-Gaussian keys and buffers, keeps working.
- ``theta_i(t)``: 23 body-joint rotations; ``G_i(t)``: global orientation relative to the
  box (world orientation = R_box G). Both start from the pose sequence in
  ``scene.human_poses`` and are refined (right-multiplied axis-angle deltas per frame,
  lr 5e-4 -> 1e-4, 10x the paper's, see docs/methods.md). Held-out frames get no image
  gradients, so their rotations are SLERPed between the refined poses of the nearest
  training frames of that person.
- ``R_box, t_box``: the shared :class:`~omnire.nodes.actors.ActorPoses` (box centre and its
  refinement; the box rotation delta is not optimised, the refined global orientation
  covers it). The template's vertical centre sits at the box centre.
- Size: each template is scaled to its box height (the shipped template is 1.63 m) unless
  the pose sequence has betas and the template shape blend shapes (then betas give the
  shape, unscaled).
- Pose blend shapes (``posedirs`` of SMPL files) are not applied: Gaussians, not vertices,
  are skinned, and densified Gaussians have no vertex of their own.

Regulariser ``pose_smoothness`` (docs/paper.md "Losses"): for the people present at t and a
random d in {1..max_offset}, 0.5 * mean |r(t-d) + r(t+d) - 2 r(t)| over the 6D rotation
features (first two matrix columns) of the 24 rotations.

Skinning runs once per frame for all people present (one FK over P bodies, one gather);
absent people cost nothing.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from omnire.api import (
    ActorNode,
    ActorState,
    Camera,
    GaussianNodeConfig,
    HumanPoseSequence,
    NodeContext,
    NodeOutput,
    ParamGroup,
    SceneTime,
    axis_angle_to_rotmat,
    colour_from_images,
    frame_blend,
    gaussian_reach,
    init_gaussian_params,
    knn_scales,
    segment_max,
    slerp_rotmats,
    train_frame_bracket,
)
from omnire_body.rest import neutral_body_pose
from omnire_body.template import BodyTemplate, load_template
from omnire_smpl.lbs import forward_kinematics, sparse_weights
from omnire_smpl.skinning import skin_gaussians

log = logging.getLogger("omnire.nodes.smpl")


@dataclasses.dataclass
class SMPLConfig(GaussianNodeConfig):
    """Pedestrians with body poses: Gaussians skinned by a body template."""

    _target: type = dataclasses.field(default_factory=lambda: SMPLNode)
    smpl_model: Optional[Path] = None
    """SMPL model pickle (e.g. SMPL_NEUTRAL.pkl, licence-restricted: bring your own) or an Anny-style .npz; default: the shipped open Anny-derived template."""
    gaussians_per_person: int = 3000
    """Gaussians per person at initialisation (area-weighted subsample of the template vertices; 0 = one per vertex)."""
    scale_to_box: bool = True
    """Scale each template to its box height (skipped when betas and shape blend shapes give the shape)."""
    pose_source: Literal["auto", "fit", "estimator", "neutral"] = "auto"
    """Starting body poses of pedestrians without a sequence from the dataset: auto (image
    estimator keypoints + LiDAR body fitter, fused), fit (LiDAR fitter only), estimator (the
    image estimator's rotations only), neutral (a standing pose)."""
    refine_poses: bool = True
    """Learn per-frame body poses and global orientations (body-pose refinement)."""
    lr_pose: float = 5e-4
    """Body pose / global orientation refinement lr (decays to lr_pose_final). The paper's
    5e-5 -> 1e-5 fine-tunes estimated poses over 30k steps; 10x that suits this CPU budget
    (2k steps) and neutral starting poses (docs/methods.md)."""
    lr_pose_final: float = 1e-4
    """Final body pose lr."""
    smoothness_max_offset: int = 5
    """Pose smoothness compares frames t-d, t, t+d with d random in 1..this."""
    refine_boxes: bool = True
    """Learn per-frame corrections of the box centre."""
    lr_box_translation: float = 5e-4
    """Box translation refinement lr."""
    prune_margin: float = 0.25
    """Prune Gaussians that leave their canonical body's bounding box by more than this (m)."""


def person_template(template: BodyTemplate, seq: HumanPoseSequence, box_height: float, scale_to_box: bool
                    ) -> tuple[np.ndarray, np.ndarray, float]:
    """Canonical vertices (V, 3) and joints (24, 3) of one person: betas applied when
    possible, vertical centre moved to the origin (= box centre), scaled to ``box_height``
    unless betas gave the shape. Returns (vertices, joints, scale)."""
    v, J = template.vertices, template.joints
    shaped = template.shapedirs is not None and seq.betas.size > 0
    if shaped:
        k = min(seq.betas.shape[-1], template.shapedirs.shape[2])
        v = v + template.shapedirs[:, :, :k] @ seq.betas[:k]
        if template.J_regressor is not None:
            J = template.J_regressor @ v
    lo, hi = v[:, 1].min(), v[:, 1].max()
    centre = np.array([0.0, (lo + hi) / 2, 0.0])
    s = box_height / (hi - lo) if scale_to_box and not shaped else 1.0
    return (v - centre) * s, (J - centre) * s, float(s)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) a third of the area of the faces around each vertex."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    out = np.zeros(len(vertices))
    np.add.at(out, faces.reshape(-1), np.repeat(area / 3, 3))
    return out


def rot6(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6): the first two columns (continuous rotation features)."""
    return R[..., :, :2].reshape(*R.shape[:-2], 6)


class SMPLNode(ActorNode):
    config: SMPLConfig

    def __init__(self, config: SMPLConfig, context: NodeContext, tracks: list) -> None:
        super().__init__(config, context, tracks, config.refine_boxes)
        scene = context.scene
        device = context.device
        template = load_template(config.smpl_model)
        self.template_source = template.source
        self.parents = [int(p) for p in template.parents]
        I, F = len(tracks), scene.num_frames
        refine = config.refine_poses
        self.delta_orient = nn.Parameter(torch.zeros(I, F, 3, device=device), requires_grad=refine)
        self.delta_body = nn.Parameter(torch.zeros(I, F, 23, 3, device=device), requires_grad=refine)
        self._init_interpolation(tracks, scene.train_frames, device)
        if context.restoring:  # every tensor below comes from the checkpoint
            for name in ("joints", "canon_bbox", "base_orient", "base_body"):
                self.register_buffer(name, torch.zeros(0, device=device))
            self.init_gaussians(context, dict)
            return
        missing = [t.track_id for t in tracks if t.track_id not in scene.human_poses]
        if missing:
            raise ValueError(f"smpl node: no pose sequence for tracks {missing}; the node type's prepare() fills "
                             "scene.human_poses before tracks are assigned")
        rng = np.random.default_rng(int(torch.randint(0, 2**31, (1,), generator=context.generator)))
        go_rel = np.tile(np.eye(3), (I, F, 1, 1))
        body = np.tile(np.eye(3), (I, F, 23, 1, 1))
        joints_all, bbox, points, colours, owners, weights, scales = [], [], [], [], [], [], []
        areas = vertex_areas(template.vertices, template.faces)
        neutral = neutral_body_pose(template.joints)
        for i, track in enumerate(tracks):
            seq = scene.human_poses[track.track_id]
            bp = np.tile(neutral, (F, 1, 1, 1)) if seq.source == "neutral" else seq.body_pose
            box_R = np.where(track.present[:, None, None], track.poses[:, :3, :3], np.eye(3))
            go_rel[i] = np.einsum("fji,fjk->fik", box_R, seq.global_orient)  # R_box^T G_world
            body[i] = bp
            verts, joints, _ = person_template(template, seq, float(track.size[2]), config.scale_to_box)
            joints_all.append(joints)
            bbox.append(np.stack([verts.min(0), verts.max(0)]))
            n = template.num_vertices if config.gaussians_per_person <= 0 else min(config.gaussians_per_person,
                                                                                   template.num_vertices)
            sel = np.sort(rng.choice(template.num_vertices, n, replace=False, p=areas / areas.sum()))
            pts = verts[sel]
            points.append(pts)
            weights.append(template.weights[sel])
            owners.append(np.full(n, i))
            scales.append(np.clip(knn_scales(pts), 0.003, 0.05))
            colours.append(self._initial_colours(scene, context.images, track, go_rel[i], body[i],
                                                 template, verts, joints, sel))
        pts = torch.as_tensor(np.concatenate(points), dtype=torch.float32)
        params = init_gaussian_params(pts, torch.as_tensor(np.concatenate(colours), dtype=torch.float32),
                                      torch.as_tensor(np.concatenate(scales), dtype=torch.float32),
                                      config.sh_degree, config.init_opacity, context.generator)
        self.init_gaussians(context, lambda: {k: v.to(device) for k, v in params.items()})
        idx, w = sparse_weights(torch.as_tensor(np.concatenate(weights), dtype=torch.float32))
        self.gaussian_buffers["instance"] = torch.as_tensor(np.concatenate(owners), dtype=torch.long, device=device)
        self.gaussian_buffers["skin_joints"] = idx.to(device)
        self.gaussian_buffers["skin_weights"] = w.to(device)
        self.register_buffer("joints", torch.as_tensor(np.stack(joints_all), dtype=torch.float32, device=device))
        self.register_buffer("canon_bbox", torch.as_tensor(np.stack(bbox), dtype=torch.float32, device=device))
        self.register_buffer("base_orient", torch.as_tensor(go_rel, dtype=torch.float32, device=device))
        self.register_buffer("base_body", torch.as_tensor(body, dtype=torch.float32, device=device))
        self._report(tracks, scene)

    # ------------------------------------------------------------------ set-up helpers
    def _init_interpolation(self, tracks: list, train_frames: np.ndarray, device) -> None:
        """Per person and frame: the training frames of that person to SLERP from (prev,
        next, weight); (f, f, 0) for its own training frames."""
        I, F = len(tracks), self.delta_body.shape[1]
        prev, nxt, w = (np.tile(np.arange(F), (I, 1)), np.tile(np.arange(F), (I, 1)), np.zeros((I, F)))
        train = np.zeros(F, bool)
        train[np.asarray(train_frames, dtype=int)] = True
        for i, track in enumerate(tracks):
            prev[i], nxt[i], w[i] = train_frame_bracket(np.flatnonzero(track.present & train), F)
        self.register_buffer("interp_prev", torch.as_tensor(prev, device=device), persistent=False)
        self.register_buffer("interp_next", torch.as_tensor(nxt, device=device), persistent=False)
        self.register_buffer("interp_w", torch.as_tensor(w, dtype=torch.float32, device=device), persistent=False)

    @staticmethod
    def _initial_colours(scene, images, track, go_rel, body, template, verts, joints, sel) -> np.ndarray:
        """Colours of the selected canonical vertices, posed at the training frame where the
        person's box is closest to a camera and projected into that frame's images."""
        from omnire_body.lbs import lbs

        frames = np.intersect1d(track.frames(), scene.train_frames)
        if images is None or len(frames) == 0:
            return np.full((len(sel), 3), 0.5, dtype=np.float32)
        cams = np.stack([c.cam_to_world[frames, :3, 3] for c in scene.cameras])  # (C, T, 3)
        dist = np.linalg.norm(cams - track.poses[frames, :3, 3][None], axis=-1).min(0)
        f = int(frames[np.argmin(dist)])
        person = dataclasses.replace(template, vertices=verts, joints=joints, shapedirs=None, posedirs=None)
        posed = lbs(person, np.eye(3), body[f], pose_blend=False).vertices[sel]
        world = posed @ (track.poses[f][:3, :3] @ go_rel[f]).T + track.poses[f][:3, 3]
        colours, _ = colour_from_images(world, scene, images, np.array([f]))
        return colours

    def _report(self, tracks: list, scene) -> None:
        """One summary line on the console; the per-pedestrian pose sources were logged by
        the node type's scene preparation (the run's log file)."""
        from collections import Counter

        from rich.console import Console

        sources = Counter(scene.human_poses[t.track_id].source for t in tracks)
        Console(stderr=True, highlight=False).print(
            f"[bold]smpl[/]: {len(tracks)} pedestrians (poses: "
            + ", ".join(f"{n} {src}" for src, n in sorted(sources.items()))
            + f"), template {Path(self.template_source).name}, {self.num_gaussians} Gaussians")

    # ------------------------------------------------------------------ poses
    def _refined(self, ids: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """(P, 24, 3, 3) refined rotations (root = orientation relative to the box) of people
        ``ids`` (P,) at their frames ``frames`` (P,)."""
        R = torch.cat([self.base_orient[ids, frames][:, None], self.base_body[ids, frames]], 1)
        if self.config.refine_poses:
            d = torch.cat([self.delta_orient[ids, frames][:, None], self.delta_body[ids, frames]], 1)
            R = R @ axis_angle_to_rotmat(d)
        return R

    def pose_rotations(self, ids: torch.Tensor, frame: int) -> torch.Tensor:
        """(P, 24, 3, 3) rotations of people ``ids`` at recorded ``frame``; frames that are
        not training frames of a person are SLERPed between its neighbouring training frames."""
        p, n, w = self.interp_prev[ids, frame], self.interp_next[ids, frame], self.interp_w[ids, frame]
        R_p = self._refined(ids, p)
        interp = w > 0
        if not bool(interp.any()):
            return R_p
        R_n = self._refined(ids[interp], n[interp])
        mixed = slerp_rotmats(R_p[interp], R_n, w[interp][:, None].expand(-1, 24))
        return R_p.index_put((torch.nonzero(interp).flatten(),), mixed)

    def rotations_at(self, ids: torch.Tensor, t: SceneTime) -> torch.Tensor:
        """(P, 24, 3, 3) rotations of people ``ids`` at moment ``t``, SLERPed between the
        enclosing recorded frames when ``t`` lies between them."""
        f0, f1, w = frame_blend(t, self.delta_body.shape[1])
        R0 = self.pose_rotations(ids, f0)
        if w == 0.0:
            return R0
        return slerp_rotmats(R0, self.pose_rotations(ids, f1), torch.full(R0.shape[:2], w, dtype=R0.dtype))

    # ------------------------------------------------------------------ Node API
    def state_at(self, t: SceneTime) -> ActorState:
        """People present at ``t``: box poses and (refined, interpolated) body rotations."""
        ids, R, tr = self.poses.at(t)
        return ActorState(ids, R, tr, self.rotations_at(ids, t) if len(ids) else None)

    def gaussians_for(self, state: ActorState, t: SceneTime, camera: Optional[Camera] = None,
                      step: Optional[int] = None) -> Optional[NodeOutput]:
        """People ``state.ids`` at their box poses, skinned with ``state.body`` (P, 24, 3, 3)
        (recorded rotations when None)."""
        ids, R_box, t_box = state.ids, state.R, state.t
        instance = self.gaussian_buffers["instance"]
        g, rows = self.present_gaussians(ids)
        rots = self.rotations_at(ids, t) if state.body is None else state.body  # (P, 24, 3, 3)
        eye = torch.eye(3, device=rots.device).expand(len(ids), 1, 3, 3)
        _, A = forward_kinematics(self.joints[ids], self.parents, torch.cat([eye, rots[:, 1:]], 1))
        lookup = torch.full((self.poses.num_instances,), -1, dtype=torch.long, device=ids.device)
        lookup[ids] = torch.arange(len(ids), device=ids.device)
        slot = lookup[instance[rows]]
        # The box placement (body-to-world rotation R_box rots[:, 0], box centre t_box) is
        # folded into the P x 24 joint transforms before blending: the skin weights of a
        # Gaussian sum to 1, so blending then placing equals placing then blending, and no
        # per-Gaussian copy of the box pose is needed.
        R_tot = R_box @ rots[:, 0]  # (P, 3, 3) body-to-world orientation
        A_world = R_tot[:, None] @ A + F.pad(t_box[:, None, :, None], (3, 0))  # (P, 24, 3, 4)
        means, quats = skin_gaussians(A_world, slot, self.gaussian_buffers["skin_joints"][rows],
                                      self.gaussian_buffers["skin_weights"][rows], g.means, g.quats)
        return NodeOutput(dataclasses.replace(g, means=means, quats=quats), rows, t)

    def instance_reach(self, state: ActorState) -> torch.Tensor:
        """Skinning moves a Gaussian at ``x`` by a blend (non-negative weights summing to 1)
        of rigid joint transforms ``A_j x = R_j (x - J_j) + G_j`` (rest joints J, posed G,
        body origin at the box centre), so whatever the pose it stays within
        ``|G_j| + |x - J_j| <= (|J_0| + bones from the root to j) + (|x - J_0| + |J_j - J_0|)``
        of the box centre; the box pose then turns it about that centre. Computed for every
        person again only when the parameters or rest joints change."""
        p = self.gaussian_params

        def every_instance() -> torch.Tensor:
            J = self.joints  # (I, 24, 3) rest joints
            root = J[:, 0]
            chain = [torch.zeros_like(root[:, 0])]  # (I,) per joint: bone lengths from the root
            for j in range(1, J.shape[1]):
                parent = self.parents[j]
                chain.append(chain[parent] + (J[:, j] - J[:, parent]).norm(dim=-1))
            spread = (J - root[:, None]).norm(dim=-1).amax(dim=1)  # (I,)
            row_root = self.joints[self.gaussian_buffers["instance"], 0]  # (N, 3)
            row_reach = (p["means"].detach() - row_root).norm(dim=-1) + gaussian_reach(p["scales"].detach())
            rows = segment_max(row_reach, self.instance_offsets())
            return root.norm(dim=-1) + torch.stack(chain, 1).amax(dim=1) + spread + rows

        sources = (p["means"], p["scales"], self.gaussian_buffers["instance"], self.joints)
        return self.reach_of_instances.get(sources, every_instance)[state.ids]

    def regularization(self, output: NodeOutput) -> dict[str, torch.Tensor]:
        """``pose_smoothness`` around the rendered (recorded) frame, for the people present there."""
        frame = output.time.index
        if not self.config.refine_poses or self.poses.num_instances == 0 or frame is None:
            return {}
        F = self.delta_body.shape[1]
        # d random in 1..max_offset, shortened near the ends of the log rather than skipped
        d = min(int(torch.randint(1, self.config.smoothness_max_offset + 1, (1,))), frame, F - 1 - frame)
        if d <= 0:
            return {}
        present = self.poses.present
        ids = torch.nonzero(present[:, frame] & present[:, frame - d] & present[:, frame + d]).flatten()
        if len(ids) == 0:
            return {}
        r = [rot6(self.pose_rotations(ids, f)) for f in (frame - d, frame, frame + d)]
        return {"pose_smoothness": 0.5 * (r[0] + r[2] - 2 * r[1]).abs().mean()}

    def param_groups(self) -> list[ParamGroup]:
        groups = super().param_groups()
        if self.config.refine_poses and self.poses.num_instances:
            groups.append(ParamGroup("human_pose", [self.delta_orient, self.delta_body], self.config.lr_pose,
                                     self.config.lr_pose_final))
        # Box rotation refinement would duplicate the global-orientation refinement: translation only.
        groups += [g for g in self.poses.param_groups(0.0, self.config.lr_box_translation) if g.name == "box_translation"]
        return groups

    @torch.no_grad()
    def extra_prune_mask(self) -> torch.Tensor:
        box = self.canon_bbox[self.gaussian_buffers["instance"]]  # (N, 2, 3)
        m = self.config.prune_margin
        x = self.gaussian_params["means"]
        return ((x < box[:, 0] - m) | (x > box[:, 1] + m)).any(dim=-1)
