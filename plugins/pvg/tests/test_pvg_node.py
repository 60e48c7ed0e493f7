"""PVG node: registration, the mean/opacity formulas against float64, per-sweep
initialisation, gradients into the PVG parameters, temporally smooth training,
densification of the extra keys, and a short training run on the tiny scene."""
import math

import numpy as np
import pytest
import torch

from omnire.data.images import ImageCache
from omnire.method import MethodConfig
from omnire.nodes.base import NodeContext
from omnire.optim import Optimizers
from omnire.plugins import load_plugins
from omnire.strategy import AbsGradStrategy, DensifyConfig
from omnire.trainer import TrainConfig, Trainer, TrainerConfig
from omnire_pvg.node import PVG_KEYS, PVGConfig, PVGNode, pvg_state
from scene_helpers import make_tiny_scene, gaussians_at


@pytest.fixture
def scene(tmp_path):
    return make_tiny_scene(tmp_path / "scene")


def small_config(**kw) -> PVGConfig:
    base = dict(voxel_size=1.0, num_far_points=100, max_lidar_points=1500)
    base.update(kw)
    return PVGConfig(**base)


def build(scene, **kw) -> PVGNode:
    ctx = NodeContext(scene, ImageCache(), 10.0, torch.device("cpu"), torch.Generator().manual_seed(0))
    return small_config(**kw).setup(context=ctx, tracks=[])


def test_method_and_node_type_are_registered():
    plugins = load_plugins()
    assert "pvg" in plugins.methods.names() and "pvg" in plugins.node_types.names()
    method = plugins.methods.get("pvg").config_factory()
    assert list(method.nodes) == ["pvg"]
    assert method.regularization_weights.get("pvg_velocity", 0) > 0


def test_formulas_match_float64():
    g = torch.Generator().manual_seed(1)
    n, period = 500, 0.2
    mu = torch.randn(n, 3, generator=g) * 10
    logit = torch.randn(n, generator=g) * 3
    tau = torch.rand(n, generator=g) - 0.5
    log_beta = torch.randn(n, generator=g) - 2.0  # includes tiny life spans: decays down to ~1e-30
    v = torch.randn(n, 3, generator=g) * 20
    for t in (-0.31, 0.0, 0.27):
        means, logits = pvg_state(mu, logit, tau, log_beta, v, t, period)
        m64, l64, t64, b64, v64 = (x.double().numpy() for x in (mu, logit, tau, log_beta, v))
        exp_means = m64 + period / (2 * np.pi) * np.sin(2 * np.pi * (t - t64) / period)[:, None] * v64
        log_o = -np.log1p(np.exp(-l64)) - 0.5 * (t - t64) ** 2 / np.exp(b64) ** 2
        np.testing.assert_allclose(means.double().numpy(), exp_means, rtol=1e-5, atol=1e-4)
        # opacity in log space (relative accuracy even for tiny opacities)
        got_log_o = torch.nn.functional.logsigmoid(logits).double().numpy()
        visible = log_o > -80  # float32 logits resolve opacities down to ~1e-35
        np.testing.assert_allclose(got_log_o[visible], log_o[visible], rtol=1e-4, atol=1e-5)
        assert np.all(np.exp(got_log_o[~visible]) < 1e-30)
        assert torch.isfinite(logits).all()


def test_init_keeps_sweep_times(scene):
    node = build(scene)
    p = node.gaussian_params
    for k in PVG_KEYS:
        assert p[k].shape[0] == node.num_gaussians
    assert torch.all(p["velocity"] == 0)
    lidar_frames = [int(f) for f in scene.train_frames if scene.lidar.points[int(f)] is not None]
    frame_times = torch.tensor([node.pvg_time(float(scene.frame_timestamps[f])) for f in lidar_frames])
    lidar_rows = p["life_span"] < math.log(1.0)  # far shell rows have the long life span
    peaks = p["life_peak"][lidar_rows]
    assert torch.isclose(peaks[:, None], frame_times[None]).any(dim=1).all()
    assert len(torch.unique(peaks)) == len(lidar_frames)  # each sweep contributed
    assert int((~lidar_rows).sum()) == 100


def test_gradients_reach_pvg_parameters(scene):
    node = build(scene)
    with torch.no_grad():
        node.gaussian_params["velocity"].normal_()
    g, rows = gaussians_at(node, 1, 0.13, step=None)  # between sweeps: sin != 0 for every Gaussian
    assert rows is None
    loss = (g.means * torch.randn_like(g.means)).sum() + torch.sigmoid(g.opacities).sum()
    loss.backward()
    for k in ("means", "opacities") + PVG_KEYS:
        grad = node.gaussian_params[k].grad
        assert grad is not None and grad.abs().sum() > 0, k


def test_eval_is_deterministic_and_smoothing_follows_formula(scene):
    node = build(scene, smooth_prob=1.0, smooth_dt=0.05)
    with torch.no_grad():
        node.gaussian_params["velocity"].normal_()
        node.gaussian_params["life_span"].fill_(math.log(0.1))
    a, _ = gaussians_at(node, 2, 0.2, step=None)
    b, _ = gaussians_at(node, 2, 0.2, step=None)
    torch.testing.assert_close(a.means, b.means)
    torch.manual_seed(3)
    g, _ = gaussians_at(node, 2, 0.2, step=5)
    torch.manual_seed(3)
    torch.rand(())  # the smoothing coin
    dt = (2.0 * float(torch.rand(())) - 1.0) * 0.05
    t = node.pvg_time(0.2)
    means, logits = node.state_at(t - dt)
    torch.testing.assert_close(g.means, means + node.average_velocity() * dt)
    torch.testing.assert_close(g.opacities, logits)
    rho = torch.exp(node.gaussian_params["life_span"]) / node.config.period
    torch.testing.assert_close(node.average_velocity(), node.gaussian_params["velocity"] * torch.exp(-rho / 2)[:, None])


def test_densification_keeps_extra_keys_consistent(scene):
    node = build(scene)
    p = node.gaussian_params
    with torch.no_grad():
        p["velocity"].normal_()
        p["life_peak"].add_(torch.randn_like(p["life_peak"]) * 0.01)
    opt = Optimizers({"pvg": node}, max_steps=100)
    # give Adam non-zero moments so their resizing is checked too
    (gaussians_at(node, 1, 0.13)[0].means.sum() + p["life_span"].sum()).backward()
    opt.step(0)
    n = node.num_gaussians
    before = {k: v.detach().clone() for k, v in p.items()}
    strategy = AbsGradStrategy(DensifyConfig(refine_start=1, refine_every=1, reset_every=0, grad_threshold=1e-6,
                                             scale_threshold=1e-9), scene_radius=10.0)
    st = strategy._node_state("pvg", node)
    grow = torch.zeros(n, dtype=torch.bool)
    grow[:10] = True
    st["grad2d"][grow] = 1.0
    st["count"][:] = 1.0
    with torch.no_grad():
        p["opacities"][-5:] = -20.0  # pruned
    report = strategy.step({"pvg": node}, opt, step=1)
    assert report["grown"] == 10 and report["pruned"] == 5
    lengths = {k: v.shape[0] for k, v in node.gaussian_params.items()}
    assert set(lengths.values()) == {n - 10 + 20 - 5}, lengths  # 10 split into 20, 5 pruned
    # split children (appended at the end) inherit the parents' PVG parameters
    for k in PVG_KEYS:
        tail = node.gaussian_params[k][-20:].detach()
        torch.testing.assert_close(tail, before[k][:10].repeat(2, *([1] * (before[k].ndim - 1))))
    adam = opt.optimizers["pvg"]
    for k in PVG_KEYS:
        state = adam.state[node.gaussian_params[k]]
        assert state["exp_avg"].shape == node.gaussian_params[k].shape


def test_short_training_lowers_loss(scene, tmp_path):
    method = MethodConfig(
        nodes={"pvg": small_config()}, regularization_weights={"pvg_velocity": 0.01},
        densify=DensifyConfig(refine_start=1000), sh_degree_interval=1000, rasterizer="auto",  # native cpu if built, else torch
    )
    tc = TrainerConfig(max_steps=40, output_dir=tmp_path, run_name="pvg", log_every=5, progress=False,
                       eval_train_views=0, checkpoint_every=1000)
    trainer = Trainer(TrainConfig("pvg", "test", method, None, tc), load_plugins(), argv=[], scene=scene)

    def mean_l1() -> float:
        with torch.no_grad():
            views = trainer.train_views[::2]
            return sum(float((trainer.recon.render_view(v).rgb - trainer.observations.image(v)).abs().mean())
                       for v in views) / len(views)

    before = mean_l1()
    v0 = trainer.model.nodes["pvg"].gaussian_params["velocity"].detach().clone()
    trainer.train()
    assert mean_l1() < 0.95 * before
    node = trainer.model.nodes["pvg"]
    assert not torch.equal(node.gaussian_params["velocity"].detach(), v0)  # velocities learn
    for prm in node.parameters():
        assert torch.isfinite(prm).all()
