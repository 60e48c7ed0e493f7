"""Deformable actor node: identity at start, gradients reach the shared network and the
embeddings only through present instances, warm-up, box regulariser, node choice."""
import copy

import numpy as np
import torch

from omnire.data.images import ImageCache
from omnire.nodes.base import NodeContext
from omnire_deformable.node import DeformableConfig, DeformableNode
from omnire_deformable.plugin import accepts

from scene_helpers import make_tiny_scene, gaussians_at, regularization_at


def build(tmp_path, **kw):
    scene = make_tiny_scene(tmp_path)
    walker = copy.deepcopy(scene.tracks[0])
    walker.track_id, walker.category, walker.class_name = "ped-1", "human", "Pedestrian"
    walker.size = np.array([0.6, 0.6, 1.7])
    walker.poses[:, 1, 3] = 1.0
    walker.present[3:] = False
    scene.tracks.append(walker)
    ctx = NodeContext(scene, ImageCache(), 3.0, torch.device("cpu"), torch.Generator().manual_seed(0), [])
    return scene, DeformableNode(DeformableConfig(mlp_depth=2, mlp_width=32, **kw), ctx, [scene.tracks[0], walker])


def test_starts_as_identity_and_trains_only_present_instances(tmp_path):
    scene, node = build(tmp_path, warmup_steps=10)
    g_warm, rows = gaussians_at(node, 4, 0.4, step=0)  # warm-up: canonical Gaussians
    g, rows2 = gaussians_at(node, 4, 0.4, step=100)
    assert torch.equal(rows, rows2)
    torch.testing.assert_close(g.means, g_warm.means)  # zero-initialised output layer
    assert torch.unique(node.gaussian_buffers["instance"][rows]).tolist() == [0]  # walker absent at frame 4
    (g.means.sum() + g.scales.sum()).backward()
    assert node.mlp.out.weight.grad.abs().sum() > 0
    # past the first update the output layer is non-zero and gradients reach the embeddings
    with torch.no_grad():
        node.mlp.out.weight.normal_(0, 0.01)
    node.zero_grad()
    g, _ = gaussians_at(node, 4, 0.4, step=100)
    (g.means.sum() + g.scales.sum()).backward()
    assert node.embeddings.grad[0].abs().sum() > 0 and node.embeddings.grad[1].abs().sum() == 0


def test_box_regulariser(tmp_path):
    scene, node = build(tmp_path)
    gaussians_at(node, 0, 0.0, step=None)
    assert float(regularization_at(node, 0, 0.0)["deformable_box"]) < 1e-3  # only in-box LiDAR margins
    with torch.no_grad():
        node.mlp.out.bias[:3] = 5.0  # push everything 5 m out of the boxes
    gaussians_at(node, 0, 0.0, step=None)
    reg = regularization_at(node, 0, 0.0)["deformable_box"]
    assert float(reg) > 5.0
    reg.backward()
    assert node.mlp.out.bias.grad[:3].abs().sum() > 0


def test_static_other_actors_fold_into_background(tmp_path):
    scene = make_tiny_scene(tmp_path)
    cone = copy.deepcopy(scene.tracks[0])
    cone.category, cone.poses[:, 0, 3] = "other", 7.0
    assert not accepts(cone, scene)
    cone.poses[:, 0, 3] = 7.0 + np.arange(len(cone.poses))
    assert accepts(cone, scene)


def test_regulariser_forgets_frames_without_instances(tmp_path):
    scene, node = build(tmp_path)
    gaussians_at(node, 0, 0.0, step=None)
    scene.tracks[0].present[:] = False
    node.poses.present[:] = False
    assert gaussians_at(node, 1, 0.1, step=None) is None
    assert regularization_at(node, 1, 0.1) == {}
