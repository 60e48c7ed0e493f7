"""SMPL node: torch LBS against the numpy reference, world placement, absent people,
gradients to the body poses, pose smoothness, held-out SLERP, restricted SMPL pickles and
a tiny training run."""
import pickle

import numpy as np
import pytest
import torch

from omnire.geometry import axis_angle_to_rotmat
from omnire_body import lbs, load_template
from omnire_body import forward_kinematics as numpy_forward_kinematics
from omnire.data.images import ImageCache
from omnire.data.scene import ActorTrack, HumanPoseSequence
from omnire.api import observed_in_training
from omnire_body.rest import BODY_TO_BOX
from omnire.io.safe_pickle import UnsafePickleError
from omnire.method import MethodConfig
from omnire.nodes.background import BackgroundConfig
from omnire.nodes.base import NodeContext
from omnire.plugins import load_plugins
from omnire.strategy import DensifyConfig
from omnire.trainer import TrainConfig, Trainer, TrainerConfig
from omnire_smpl.lbs import blend_transforms, forward_kinematics, kinematic_levels, sparse_weights
from omnire_smpl.node import SMPLConfig, SMPLNode, person_template
from omnire_smpl.plugin import accepts, prepare_scene

from scene_helpers import make_tiny_scene, gaussians_at, regularization_at


def add_pedestrian(scene, track_id="ped-1", x=6.0, y=-1.2, present=None, with_poses=True, seed=0):
    """A 1.75 m pedestrian walking along +x in front of the cameras (optionally with a
    random SMPL pose sequence in scene.human_poses)."""
    F = scene.num_frames
    poses = np.tile(np.eye(4), (F, 1, 1))
    poses[:, 0, 3] = x + 0.1 * np.arange(F)
    poses[:, 1, 3] = y
    poses[:, 2, 3] = -1.5 + 0.875
    present = np.ones(F, bool) if present is None else present
    track = ActorTrack(track_id, "Pedestrian", "human", poses, np.array([0.6, 0.6, 1.75]), present)
    scene.tracks.append(track)
    if with_poses:
        rng = np.random.default_rng(seed)
        bp = axis_angle_to_rotmat(rng.normal(0, 0.3, (F, 23, 3)))
        go = poses[:, :3, :3] @ BODY_TO_BOX @ axis_angle_to_rotmat(rng.normal(0, 0.1, (F, 3)))
        scene.human_poses[track_id] = HumanPoseSequence(track_id, go, bp, np.zeros(0), np.ones(F, bool), "test")
    return track


def context(scene):
    return NodeContext(scene, ImageCache(), 5.0, torch.device("cpu"), torch.Generator().manual_seed(0), [])


def test_identity_pose_returns_template():
    t = load_template()
    J = torch.as_tensor(t.joints, dtype=torch.float32)[None]
    rots = torch.eye(3).expand(1, 24, 3, 3)
    _, A = forward_kinematics(J, [int(p) for p in t.parents], rots)
    idx, w = sparse_weights(torch.as_tensor(t.weights, dtype=torch.float32))
    T = blend_transforms(A, torch.zeros(t.num_vertices, dtype=torch.long), idx, w)
    v = torch.as_tensor(t.vertices, dtype=torch.float32)
    out = torch.einsum("mij,mj->mi", T[:, :, :3], v) + T[:, :, 3]
    torch.testing.assert_close(out, v, atol=1e-5, rtol=0)


def test_forward_kinematics_by_levels_matches_the_numpy_chain_in_float64():
    """The level-at-a-time chain against omnire_body's joint-by-joint float64 reference:
    posed joints and skinning transforms, on a tree whose levels are not contiguous."""
    t = load_template()
    assert [len(level) for level in kinematic_levels([int(p) for p in t.parents])][:2] == [1, 3]
    rng = np.random.default_rng(5)
    go = axis_angle_to_rotmat(rng.normal(0, 0.8, (3, 3)))
    bp = axis_angle_to_rotmat(rng.normal(0, 0.6, (3, 23, 3)))
    posed_ref, skin_ref = numpy_forward_kinematics(t.joints, t.parents, go, bp)
    J = torch.as_tensor(np.broadcast_to(t.joints, (3, 24, 3)).copy())
    rots = torch.as_tensor(np.concatenate([go[:, None], bp], 1))
    posed, A = forward_kinematics(J, [int(p) for p in t.parents], rots)
    np.testing.assert_allclose(posed.numpy(), posed_ref, atol=1e-12)
    np.testing.assert_allclose(A.numpy(), skin_ref[:, :, :3], atol=1e-12)
    with pytest.raises(ValueError, match=r"parents\[2\] = 3"):
        kinematic_levels([-1, 0, 3, 1])


def test_batched_lbs_matches_numpy_reference():
    t = load_template()
    rng = np.random.default_rng(3)
    go = axis_angle_to_rotmat(rng.normal(0, 0.5, (2, 3)))
    bp = axis_angle_to_rotmat(rng.normal(0, 0.4, (2, 23, 3)))
    ref = lbs(t, go, bp, pose_blend=False).vertices  # (2, V, 3) float64
    J = torch.as_tensor(np.stack([t.joints, t.joints]), dtype=torch.float32)
    rots = torch.as_tensor(np.concatenate([go[:, None], bp], 1), dtype=torch.float32)
    _, A = forward_kinematics(J, [int(p) for p in t.parents], rots)
    idx, w = sparse_weights(torch.as_tensor(t.weights, dtype=torch.float32))
    V = t.num_vertices
    slot = torch.cat([torch.zeros(V, dtype=torch.long), torch.ones(V, dtype=torch.long)])
    T = blend_transforms(A, slot, idx.repeat(2, 1), w.repeat(2, 1))
    v = torch.as_tensor(t.vertices, dtype=torch.float32).repeat(2, 1)
    out = (torch.einsum("mij,mj->mi", T[:, :, :3], v) + T[:, :, 3]).reshape(2, V, 3)
    np.testing.assert_allclose(out.numpy(), ref, atol=2e-5)


def test_blend_per_body_products_match_the_per_point_gather():
    """Points grouped by body (one matrix product per body) against the same points shuffled
    (the per-point gather), float64: values, and the gradient of A by gradcheck; a body with
    no points and a joint index repeated within a point are covered."""
    g = torch.Generator().manual_seed(0)
    P, J, M, K = 4, 24, 300, 5
    A = torch.randn(P, J, 3, 4, dtype=torch.float64, generator=g, requires_grad=True)
    slot = torch.randint(0, P, (M,), generator=g).clamp(max=P - 2).sort().values  # body P-1: none
    joint_idx = torch.randint(0, J, (M, K), generator=g)
    joint_idx[:, 1] = joint_idx[:, 0]  # repeated joints add up, as in the gather
    weights = torch.rand(M, K, dtype=torch.float64, generator=g)
    perm = torch.randperm(M, generator=g)
    grouped = blend_transforms(A, slot, joint_idx, weights)
    shuffled = blend_transforms(A, slot[perm], joint_idx[perm], weights[perm])
    torch.testing.assert_close(grouped[perm], shuffled, rtol=1e-12, atol=1e-12)
    upstream = torch.randn(M, 3, 4, dtype=torch.float64, generator=g)
    (grad_grouped,) = torch.autograd.grad((grouped * upstream).sum(), A)
    (grad_shuffled,) = torch.autograd.grad((shuffled * upstream[perm]).sum(), A)
    torch.testing.assert_close(grad_grouped, grad_shuffled, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(lambda a: blend_transforms(a, slot[:40], joint_idx[:40], weights[:40]), (A,))


def test_node_places_people_like_numpy_and_skips_absent(tmp_path):
    scene = make_tiny_scene(tmp_path, holdout=0)
    present = np.ones(scene.num_frames, bool)
    present[2] = False
    track = add_pedestrian(scene, present=present)
    node = SMPLNode(SMPLConfig(gaussians_per_person=0, refine_boxes=False), context(scene), [track])
    assert gaussians_at(node, 2, 0.0) is None  # absent: nothing, no cost
    f = 3
    g, rows = gaussians_at(node, f, 0.0)
    assert len(rows) == node.num_gaussians == load_template().num_vertices
    # Independent placement: numpy LBS of the scaled person template (identity root),
    # then the world orientation of the sequence and the box centre.
    tmpl = load_template()
    seq = scene.human_poses[track.track_id]
    verts, joints, s = person_template(tmpl, seq, 1.75, True)
    assert abs(s - 1.75 / np.ptp(tmpl.vertices[:, 1])) < 1e-9
    person = type(tmpl)(verts, tmpl.faces, joints, tmpl.parents, tmpl.weights)
    canon = node.gaussian_params["means"].detach().double().numpy()
    person.vertices = canon  # the Gaussians sit exactly on the (scaled) vertices at init
    np.testing.assert_allclose(canon, verts, atol=1e-5)
    posed = lbs(person, np.eye(3), seq.body_pose[f], pose_blend=False).vertices
    expect = posed @ seq.global_orient[f].T + track.poses[f][:3, 3]
    np.testing.assert_allclose(g.means.detach().numpy(), expect, atol=1e-4)
    # The person stands upright in the box: feet near the ground, head near the box top.
    z = g.means[:, 2].detach()
    assert float(z.max() - z.min()) > 1.2


def test_box_placement_folded_into_joint_transforms_matches_per_gaussian_placement(tmp_path):
    """The node places the blended transforms by folding the box pose into the 24 joint
    transforms; the same Gaussians placed one by one (blend, then R_box R_root and the box
    centre per row) agree, quaternions included, for two people, one of them refined."""
    from omnire.data.scene import SceneTime
    from omnire.geometry import quat_multiply, rotmat_to_quat

    scene = make_tiny_scene(tmp_path, holdout=0)
    tracks = [add_pedestrian(scene, "ped-1", seed=1), add_pedestrian(scene, "ped-2", x=8.0, y=1.0, seed=2)]
    node = SMPLNode(SMPLConfig(gaussians_per_person=0), context(scene), tracks)
    with torch.no_grad():
        node.delta_body.normal_(0, 0.05, generator=torch.Generator().manual_seed(0))
        node.poses.delta_t.normal_(0, 0.1, generator=torch.Generator().manual_seed(1))
    t = SceneTime(3, 0.0)
    out = node.gaussians_at(t, None, None)
    state = node.state_at(t)
    g, rows = node.present_gaussians(state.ids)
    rots = node.rotations_at(state.ids, t).double()
    eye = torch.eye(3, dtype=torch.float64).expand(len(state.ids), 1, 3, 3)
    _, A = forward_kinematics(node.joints[state.ids].double(), node.parents, torch.cat([eye, rots[:, 1:]], 1))
    slot = torch.searchsorted(state.ids, node.gaussian_buffers["instance"][rows])
    T = blend_transforms(A, slot, node.gaussian_buffers["skin_joints"][rows],
                         node.gaussian_buffers["skin_weights"][rows].double())
    R_tot = (state.R.double() @ rots[:, 0])[slot]
    R_full = R_tot @ T[:, :, :3]
    means = (R_full @ g.means.double()[..., None])[..., 0] + (R_tot @ T[:, :, 3:])[..., 0] + state.t.double()[slot]
    quats = quat_multiply(rotmat_to_quat(R_full), g.quats.double())
    torch.testing.assert_close(out.gaussians.means.double(), means, atol=2e-5, rtol=0)
    torch.testing.assert_close(out.gaussians.quats.double(), quats, atol=2e-5, rtol=0)


def test_gradients_reach_pose_parameters_and_smoothness(tmp_path):
    scene = make_tiny_scene(tmp_path, frames=12, holdout=4)
    track = add_pedestrian(scene)
    node = SMPLNode(SMPLConfig(gaussians_per_person=500), context(scene), [track])
    g, _ = gaussians_at(node, 5, 0.0)
    g.means.sum().backward()
    assert node.delta_body.grad[0, 5].abs().sum() > 0 and node.delta_orient.grad[0, 5].abs().sum() > 0
    assert node.delta_body.grad[0, 6].abs().sum() == 0  # other frames untouched
    assert node.poses.delta_t.grad[0, 5].abs().sum() > 0
    node.zero_grad()
    torch.manual_seed(0)
    reg = regularization_at(node, 6, 0.0)
    assert set(reg) == {"pose_smoothness"} and float(reg["pose_smoothness"].detach()) > 0  # random poses are not smooth
    reg["pose_smoothness"].backward()
    assert node.delta_body.grad.abs().sum() > 0
    names = {grp.name: grp for grp in node.param_groups()}
    assert (names["human_pose"].lr, names["human_pose"].lr_final) == (node.config.lr_pose, node.config.lr_pose_final)
    assert "box_translation" in names and "box_rotation" not in names


def test_held_out_frames_slerp_between_refined_neighbours(tmp_path):
    scene = make_tiny_scene(tmp_path, frames=9, holdout=4)  # frames 4 and 8 held out
    track = add_pedestrian(scene)
    node = SMPLNode(SMPLConfig(gaussians_per_person=200), context(scene), [track])
    with torch.no_grad():
        node.delta_body[0, 3, 0] = torch.tensor([0.2, 0.0, 0.0])
    ids = torch.tensor([0])
    R3, R4, R5 = (node.pose_rotations(ids, f)[0] for f in (3, 4, 5))
    from omnire_smpl.node import slerp_rotmats

    torch.testing.assert_close(R4, slerp_rotmats(R3, R5, torch.full((24,), 0.5)), atol=1e-5, rtol=0)
    # Frame 8 (held out, last) holds frame 7.
    torch.testing.assert_close(node.pose_rotations(ids, 8), node.pose_rotations(ids, 7), atol=1e-6, rtol=0)


def test_smpl_pickle_that_runs_code_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            import os
            return (os.system, ("echo pwned > " + str(tmp_path / "pwned"),))

    evil = tmp_path / "SMPL_NEUTRAL.pkl"
    evil.write_bytes(pickle.dumps({"v_template": Evil(), "weights": np.zeros((3, 24))}))
    scene = make_tiny_scene(tmp_path / "s")
    track = add_pedestrian(scene)
    with pytest.raises(UnsafePickleError, match="SMPL_NEUTRAL.pkl.*system"):
        SMPLNode(SMPLConfig(smpl_model=evil), context(scene), [track])
    assert not (tmp_path / "pwned").exists()


def test_prepare_fills_neutral_poses_and_accepts_is_pure(tmp_path):
    scene = make_tiny_scene(tmp_path)
    track = add_pedestrian(scene, with_poses=False)
    hidden = add_pedestrian(scene, "behind", x=-30.0, with_poses=False)
    assert not accepts(track, scene) and scene.human_poses == {}  # a predicate: prepares nothing
    prepare_scene(scene, load_plugins(disabled={"pose_mediapipe", "omnire-pose-mediapipe"}))
    assert accepts(track, scene)
    # no camera sees it: the core keeps it in the background (accepts leaves that to the core)
    assert accepts(hidden, scene) and not observed_in_training(hidden, scene, lidar_learning=False)
    seq = scene.human_poses[track.track_id]
    assert seq.source == "neutral" and not seq.valid.any()
    # Facing the heading: the body's forward axis (+z) is the box x axis.
    np.testing.assert_allclose(seq.global_orient[0] @ [0, 0, 1.0], track.poses[0][:3, 0], atol=1e-9)
    # Arms hang down: the elbows are below the shoulders in the neutral pose.
    t = load_template()
    from omnire_body import forward_kinematics as fk

    J, _ = fk(t.joints, t.parents, np.eye(3), seq.body_pose[0])
    assert J[18, 1] < J[16, 1] - 0.2 and J[19, 1] < J[17, 1] - 0.2


def test_tiny_training_run(tmp_path):
    scene = make_tiny_scene(tmp_path / "scene", frames=8, width=32, height=24, holdout=4)
    add_pedestrian(scene, x=5.0, y=-0.8)
    method = MethodConfig(
        nodes={"background": BackgroundConfig(voxel_size=0.8, num_far_points=100),
               "smpl": SMPLConfig(gaussians_per_person=300, lr_pose=5e-3, lr_pose_final=1e-3)},
        regularization_weights={"pose_smoothness": 0.01},
        densify=DensifyConfig(refine_start=4, refine_every=4, reset_every=0, grad_threshold=1e-5),
        sh_degree_interval=15, rasterizer="auto")  # native cpu if built, else torch
    tc = TrainerConfig(max_steps=12, output_dir=tmp_path, run_name="run", progress=False)
    trainer = Trainer(TrainConfig("smpl-test", "test", method, None, tc), load_plugins(), argv=[], scene=scene)
    assert trainer.recon.assignment["smpl"] == ["ped-1"]
    node = trainer.model.nodes["smpl"]
    before, n0 = node.delta_body.detach().clone(), node.num_gaussians
    torch.manual_seed(1)
    stats = [trainer.train_step() for _ in range(12)]
    assert (node.delta_body.detach() - before).abs().max() > 0
    assert any("pose_smoothness" in s for s in stats)
    assert node.num_gaussians != n0  # densified through the generic strategy
    assert node.gaussian_buffers["skin_weights"].shape[0] == node.num_gaussians
    g, _ = gaussians_at(node, 1, 0.0)
    assert torch.isfinite(g.means).all()
    for p in trainer.model.parameters():
        assert torch.isfinite(p).all()


def test_instance_reach_holds_every_gaussian_in_any_pose(tmp_path):
    """The ball :meth:`SMPLNode.instance_reach` gives each person (around the box centre)
    contains every skinned Gaussian's mean plus 4 times its largest scale, for random poses
    far from the fitted ones (brute force over the placed Gaussians), and is not much looser
    than the body itself."""
    from omnire.api import CULL_SIGMAS, ActorState
    from omnire.data.scene import SceneTime

    scene = make_tiny_scene(tmp_path, holdout=0)
    tracks = [add_pedestrian(scene, "ped-1", seed=1), add_pedestrian(scene, "ped-2", x=8.0, y=1.0, seed=2)]
    node = SMPLNode(SMPLConfig(gaussians_per_person=0), context(scene), tracks)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        node.gaussian_params["scales"].add_(torch.randn(node.num_gaussians, 3, generator=gen))
    t = SceneTime(2, 0.0)
    base = node.state_at(t)
    for trial in range(5):
        body = axis_angle_to_rotmat(torch.randn(2, 24, 3, generator=gen) * 1.5)  # any joint angles
        state = ActorState(base.ids, base.R, base.t, body)
        with torch.no_grad():
            out = node.gaussians_for(state, t)
            reach = node.instance_reach(state)
        owner = torch.searchsorted(state.ids, node.gaussian_buffers["instance"][out.rows])
        g = out.gaussians
        far = (g.means - state.t[owner]).norm(dim=-1) + CULL_SIGMAS * g.scales.amax(dim=-1).exp()
        per_person = torch.zeros(2).scatter_reduce(0, owner, far, "amax")
        assert bool((per_person <= reach + 1e-4).all()), (trial, per_person, reach)
        assert bool((reach < 3 * per_person).all())  # a bound that still culls
