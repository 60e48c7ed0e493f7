"""DeformableGS node: registration, warm-up, stop-gradient, gradients into the MLP,
densification with the MLP attached, and a short training run on the tiny scene."""
import json

import pytest
import torch

from omnire.data.images import ImageCache
from omnire.method import MethodConfig
from omnire.nodes.base import NodeContext
from omnire.optim import Optimizers
from omnire.plugins import load_plugins
from omnire.strategy import AbsGradStrategy, DensifyConfig
from omnire.trainer import TrainConfig, Trainer, TrainerConfig
from omnire.nn import positional_encoding
from omnire_deformablegs.node import DeformableFieldConfig, DeformableFieldNode
from scene_helpers import make_tiny_scene, gaussians_at


@pytest.fixture
def scene(tmp_path):
    return make_tiny_scene(tmp_path / "scene")


def small_config(**kw) -> DeformableFieldConfig:
    base = dict(voxel_size=1.0, num_far_points=100, warmup_steps=3, mlp_depth=4, mlp_width=32)
    base.update(kw)
    return DeformableFieldConfig(**base)


def build(scene, **kw) -> DeformableFieldNode:
    ctx = NodeContext(scene, ImageCache(), 10.0, torch.device("cpu"), torch.Generator().manual_seed(0))
    return small_config(**kw).setup(context=ctx, tracks=[])


def test_method_and_node_type_are_registered():
    plugins = load_plugins()
    assert "deformablegs" in plugins.methods.names()
    assert "deformable_field" in plugins.node_types.names()
    method = plugins.methods.get("deformablegs").config_factory()
    assert list(method.nodes) == ["deformable_field"]
    assert method.loss_weights == MethodConfig().loss_weights  # same losses as 3dgs
    assert plugins.node_types.get("deformable_field").categories == frozenset()  # no boxes


def test_positional_encoding_layout():
    x = torch.tensor([[0.25, -0.5, 1.0]])
    enc = positional_encoding(x, 2)
    assert enc.shape == (1, 12)
    expected_sin = torch.sin(torch.tensor([0.25, -0.5, 1.0, 0.5, -1.0, 2.0]) * torch.pi)
    torch.testing.assert_close(enc[0, :6], expected_sin)


def test_warmup_renders_canonical_then_deforms(scene):
    node = build(scene)
    with torch.no_grad():
        node.mlp.out.weight.normal_(0, 0.1)
    p = node.gaussian_params
    g, rows = gaussians_at(node, 0, 0.0, step=0)  # warm-up: the canonical Gaussians themselves
    assert rows is None and g.means is p["means"]
    g2, _ = gaussians_at(node, 0, 0.0, step=10)
    g3, _ = gaussians_at(node, 0, 0.0, step=None)  # evaluation: always deformed
    assert not torch.allclose(g2.means, p["means"])
    torch.testing.assert_close(g3.means, gaussians_at(node, 0, 0.0, step=None)[0].means)  # no noise at eval
    # time enters the field: another frame time moves the Gaussians differently
    g4, _ = gaussians_at(node, 5, 0.5, step=None)
    assert not torch.allclose(g3.means, g4.means)


def test_fresh_field_is_identity(scene):
    node = build(scene)
    g, _ = gaussians_at(node, 2, 0.2, step=None)
    p = node.gaussian_params
    torch.testing.assert_close(g.means, p["means"])
    torch.testing.assert_close(g.scales, p["scales"])
    torch.testing.assert_close(g.quats, p["quats"] / p["quats"].norm(dim=-1, keepdim=True))


def test_gradients_reach_every_mlp_parameter_and_position_input_is_stopped(scene):
    node = build(scene)
    with torch.no_grad():
        node.mlp.out.weight.normal_(0, 0.1)
    g, _ = gaussians_at(node, 1, 0.1, step=None)
    w = torch.randn_like(g.means)
    loss = (g.means * w).sum() + g.scales.square().sum() + g.quats.square().sum()
    loss.backward()
    for name, prm in node.mlp.named_parameters():
        assert prm.grad is not None and prm.grad.abs().sum() > 0, name
    # sg(x): the canonical means get exactly the direct gradient, nothing through the field
    torch.testing.assert_close(node.gaussian_params["means"].grad, w)


def test_densification_keeps_tensors_consistent_and_mlp_in_optimizer(scene):
    node = build(scene)
    opt = Optimizers({"deformable_field": node}, max_steps=100)
    strategy = AbsGradStrategy(DensifyConfig(refine_start=1, refine_every=1, reset_every=0, grad_threshold=1e-6),
                               scene_radius=10.0)
    n = node.num_gaussians
    st = strategy._node_state("deformable_field", node)
    st["grad2d"][: n // 2] = 1.0
    st["count"][:] = 1.0
    with torch.no_grad():
        node.gaussian_params["opacities"][-3:] = -20.0  # pruned
    strategy.step({"deformable_field": node}, opt, step=1)
    lengths = {k: v.shape[0] for k, v in node.gaussian_params.items()}
    assert len(set(lengths.values())) == 1 and node.num_gaussians != n
    mlp_group = [g for g in opt.groups["deformable_field"] if g.name == "deformation_mlp"][0]
    assert {id(p) for p in mlp_group.params} == {id(p) for p in node.mlp.parameters()}


def test_short_training_lowers_loss(scene, tmp_path):
    method = MethodConfig(
        nodes={"deformable_field": small_config(warmup_steps=10)},
        densify=DensifyConfig(refine_start=1000), sh_degree_interval=1000, rasterizer="auto",  # native cpu if built, else torch
    )
    tc = TrainerConfig(max_steps=40, output_dir=tmp_path, run_name="dgs", log_every=5, progress=False,
                       eval_train_views=0, checkpoint_every=1000)
    trainer = Trainer(TrainConfig("deformablegs", "test", method, None, tc), load_plugins(), argv=[], scene=scene)

    def mean_l1() -> float:
        with torch.no_grad():
            views = trainer.train_views[::2]
            return sum(float((trainer.recon.render_view(v).rgb - trainer.observations.image(v)).abs().mean())
                       for v in views) / len(views)

    before = mean_l1()
    trainer.train()
    after = mean_l1()
    assert after < 0.95 * before
    logs = [json.loads(line) for line in (trainer.run_dir / "metrics.jsonl").read_text().splitlines()]
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in logs if "loss" in r)
    # the field was trained after the warm-up
    assert trainer.model.nodes["deformable_field"].mlp.out.weight.abs().sum() > 0


def test_frustum_culling_deforms_only_what_the_camera_sees_and_renders_the_same(scene, tmp_path):
    method = MethodConfig(nodes={"deformable_field": small_config(warmup_steps=0)}, rasterizer="auto")
    tc = TrainerConfig(max_steps=1, output_dir=tmp_path, run_name="cull", progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig("deformablegs", "test", method, None, tc), load_plugins(), argv=[], scene=scene)
    node = trainer.model.nodes["deformable_field"]
    with torch.no_grad():
        node.mlp.out.weight.normal_(0, 0.01)
        # Far behind every camera: never deformed, never rendered.
        node.gaussian_params["means"][:50] = trainer.recon.camera(trainer.train_views[0]).center - 1e4
    view = trainer.train_views[0]
    g, rows = gaussians_at(node, view.frame, 0.1, step=None, camera=trainer.recon.camera(view))
    assert rows is not None and 0 < len(rows) < node.num_gaussians and not bool((rows < 50).any())
    full, _ = gaussians_at(node, view.frame, 0.1, step=None)  # no camera: every Gaussian
    torch.testing.assert_close(g.means, full.means[rows])
    with torch.no_grad():
        culled = trainer.recon.render_view(view).rgb
        node.config.cull_margin = -1.0  # off: the paper's behaviour
        uncull = trainer.recon.render_view(view).rgb
    torch.testing.assert_close(culled, uncull, atol=1e-4, rtol=0)
