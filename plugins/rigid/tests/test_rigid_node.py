"""Rigid node: world placement, absent actors, box refinement recovering a perturbed
trajectory, and bad tracks."""
import copy
import warnings

import numpy as np
import pytest
import torch

from omnire.data.scene import SceneDataError
from omnire.gaussians import rgb_to_sh0
from omnire.nodes.base import NodeContext
from omnire.data.images import ImageCache
from omnire.plugins import load_plugins
from omnire.rasterization import RasterSettings, Splats, select_rasterizer
from omnire_rigid.node import RigidConfig, RigidNode
from omnire_rigid.plugin import accepts

from scene_helpers import make_tiny_scene, gaussians_at


def context(scene, excluded=()):
    return NodeContext(scene, ImageCache(), 5.0, torch.device("cpu"), torch.Generator().manual_seed(0), list(excluded))


def yaw_pose(x, y, z, yaw):
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


def textured_box(node, n=400, seed=0):
    """Replace the node's Gaussians by opaque coloured splats on the box surface."""
    g = torch.Generator().manual_seed(seed)
    half = node.half_sizes[0]
    p = (torch.rand(n, 3, generator=g) * 2 - 1) * half
    axis = torch.randint(0, 3, (n,), generator=g)
    side = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0)
    p[torch.arange(n), axis] = side * half[axis]
    with torch.no_grad():
        node.set_gaussian_tensors({
            "means": p, "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
            "scales": torch.full((n, 3), np.log(0.12)), "opacities": torch.full((n,), 3.0),
            "sh0": rgb_to_sh0(torch.rand(n, 3, generator=g)), "shN": torch.zeros(n, 15, 3),
            "instance": torch.zeros(n, dtype=torch.long),
        })


def render(node, scene, view, rast):
    g, _ = gaussians_at(node, view.frame, 0.0)
    camera = scene.camera(view)
    splats = Splats(g.means, g.quats, g.activated_scales, g.activated_opacities, g.colors(camera.center, 0))
    return rast.rasterize(splats, camera, RasterSettings(background=torch.zeros(3))).rgb


def test_world_placement_and_absence(tmp_path):
    scene = make_tiny_scene(tmp_path)
    track = scene.tracks[0]
    track.present[2] = False
    node = RigidNode(RigidConfig(), context(scene), [track])
    g, rows = gaussians_at(node, 0, 0.0)
    local = node.gaussian_params["means"][rows]
    expect = local.detach() @ torch.as_tensor(track.poses[0][:3, :3], dtype=torch.float32).T + \
        torch.as_tensor(track.poses[0][:3, 3], dtype=torch.float32)
    torch.testing.assert_close(g.means.detach(), expect)
    assert gaussians_at(node, 2, 0.0) is None  # absent: nothing, no cost
    assert node.num_gaussians > 300


def test_box_refinement_moves_poses_toward_truth(tmp_path):
    scene = make_tiny_scene(tmp_path, frames=4, width=64, height=48, holdout=0)
    truth = scene.tracks[0]
    for f in range(4):
        truth.poses[f] = yaw_pose(7.0 + 0.3 * f, 0.5, -0.6, 0.2 + 0.05 * f)
    noisy = copy.deepcopy(truth)
    rng = np.random.default_rng(1)
    for f in range(4):
        noisy.poses[f] = truth.poses[f] @ yaw_pose(*rng.normal(0, 0.25, 2), 0.0, rng.normal(0, 0.06))
    rast = select_rasterizer(load_plugins(), "torch")
    ref = RigidNode(RigidConfig(refine_boxes=False), context(scene), [truth])
    textured_box(ref)
    views = [v for v in scene.views(np.arange(4))]
    targets = {v: render(ref, scene, v, rast).detach() for v in views}
    node = RigidNode(RigidConfig(), context(scene), [noisy])
    textured_box(node)
    for p in node.gaussian_params.values():
        p.requires_grad_(False)
    opt = torch.optim.Adam([node.poses.delta_rot, node.poses.delta_t], lr=0.01)

    def error():
        errs = []
        for f in range(4):
            _, R, t = node.poses.at_frame(f)
            errs.append(float(np.linalg.norm(t[0].detach().numpy() - truth.poses[f][:3, 3])))
        return np.mean(errs)

    before = error()
    for it in range(150):
        v = views[it % len(views)]
        loss = (render(node, scene, v, rast) - targets[v]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = error()
    assert after < 0.35 * before, (before, after)


def test_bad_tracks(tmp_path):
    scene = make_tiny_scene(tmp_path)
    bad = copy.deepcopy(scene.tracks[0])
    bad.track_id, bad.size = "flat-car", np.array([4.0, 0.0, 1.5])
    with pytest.warns(UserWarning, match="flat-car"):
        assert not accepts(bad, scene)
    nan = copy.deepcopy(scene.tracks[0])
    nan.track_id = "nan-car"
    nan.poses[1, 1, 3] = np.nan
    scene.tracks.append(nan)
    with pytest.raises(SceneDataError, match="nan-car"):
        scene.validate()
    scene.tracks.pop()
    single = copy.deepcopy(scene.tracks[0])
    single.track_id = "blink"
    single.present[:] = False
    single.present[1] = True
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        node = RigidNode(RigidConfig(), context(scene), [single])
    assert gaussians_at(node, 0, 0.0) is None
    g, _ = gaussians_at(node, 1, 0.0)
    assert torch.isfinite(g.means).all() and len(g) > 0


def test_instance_reach_holds_every_gaussian(tmp_path):
    """Each actor's ball (:meth:`BoxActorNode.instance_reach`, around the box centre) holds
    its Gaussians' means plus 4 times their largest scales (brute force), tightly; an actor
    whose Gaussians were all pruned gets 0."""
    from omnire.api import CULL_SIGMAS
    from omnire.data.scene import SceneTime

    scene = make_tiny_scene(tmp_path)
    scene.tracks.append(copy.deepcopy(scene.tracks[0]))
    scene.tracks[1].track_id = "car-2"
    scene.tracks[1].poses[:, 1, 3] += 3.0
    node = RigidNode(RigidConfig(), context(scene), scene.tracks)
    with torch.no_grad():
        node.gaussian_params["scales"].add_(torch.randn(node.num_gaussians, 3, generator=torch.Generator().manual_seed(0)))
    state = node.state_at(SceneTime(1, 0.0))
    out = node.gaussians_for(state, SceneTime(1, 0.0))
    owner = torch.searchsorted(state.ids, node.gaussian_buffers["instance"][out.rows])
    far = (out.gaussians.means - state.t[owner]).norm(dim=-1) + CULL_SIGMAS * out.gaussians.scales.amax(dim=-1).exp()
    per_actor = torch.zeros(len(state.ids)).scatter_reduce(0, owner, far.detach(), "amax")
    torch.testing.assert_close(node.instance_reach(state), per_actor, rtol=1e-5, atol=1e-5)
    keep = node.gaussian_buffers["instance"] == 1  # prune the first actor's Gaussians
    for k in list(node.gaussian_params):
        node.gaussian_params[k] = torch.nn.Parameter(node.gaussian_params[k].detach()[keep])
    node.gaussian_buffers["instance"] = node.gaussian_buffers["instance"][keep]
    assert float(node.instance_reach(state)[0]) == 0.0
