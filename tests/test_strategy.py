"""AbsGrad densification: clone / split / prune / reset keep every per-Gaussian tensor and
its Adam moments consistent."""
import math

import pytest
import torch

from omnire.errors import ConfigError
from omnire.nodes.base import Node, init_gaussian_params
from omnire.optim import Optimizers, exponential_lr
from omnire.strategy import AbsGradStrategy, DensifyConfig, NodeSlice


class ToyNode(Node):
    def __init__(self, n=6):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        params = init_gaussian_params(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g),
                                      torch.full((n,), 0.1), 1, 0.5, g)
        params["velocity"] = torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 3)
        for k, v in params.items():
            self.gaussian_params[k] = torch.nn.Parameter(v)
        self.gaussian_buffers["owner"] = torch.arange(n)

    def gaussian_lrs(self):
        return {k: (1e-2, None) for k in self.gaussian_params.keys()}


def setup(n=6):
    node = ToyNode(n)
    opt = Optimizers({"toy": node}, max_steps=100)
    # one real optimiser step so Adam has moments to carry along
    sum((p ** 2).sum() for p in node.gaussian_params.values()).backward()
    opt.step(0)
    opt.zero_grad()
    return node, opt


def lengths(node, opt):
    out = {k: p.shape[0] for k, p in node.gaussian_params.items()}
    out.update({k: b.shape[0] for k, b in node.gaussian_buffers.items()})
    for group in opt.optimizers["toy"].param_groups:
        p = group["params"][0]
        st = opt.optimizers["toy"].state[p]
        out[group["name"] + ".exp_avg"] = st["exp_avg"].shape[0]
        assert p is node.gaussian_params[group["name"]]
    return set(out.values())


def test_clone_split_prune_keep_tensors_consistent():
    node, opt = setup(6)
    cfg = DensifyConfig(refine_start=0, refine_every=1, reset_every=0, grad_threshold=0.1, scale_threshold=0.5)
    strat = AbsGradStrategy(cfg, scene_radius=1.0)
    with torch.no_grad():
        node.gaussian_params["scales"][:3] = math.log(0.1)  # small -> clone
        node.gaussian_params["scales"][3:] = math.log(2.0)  # large -> split
        node.gaussian_params["opacities"][5] = -10.0  # prune (after split copies it)
    absgrad = torch.tensor([[1.0, 1.0], [1e-5, 0], [1.0, 0], [1.0, 1.0], [0, 1e-6], [1.0, 1.0]])
    strat.accumulate({"toy": node}, [NodeSlice("toy", 0, 6, None)], absgrad, torch.ones(6, dtype=torch.int32), 2, 2)
    means_before = node.gaussian_params["means"].detach().clone()
    velocity_before = node.gaussian_params["velocity"].detach().clone()
    report = strat.step({"toy": node}, opt, 1)
    # grown: 2 clones (rows 0, 2) + 2 splits (rows 3, 5); pruned: both halves of row 5
    assert report == {"grown": 4, "pruned": 2}
    assert lengths(node, opt) == {6 + 2 + 2 - 2}
    owners = node.gaussian_buffers["owner"].tolist()
    assert sorted(owners) == [0, 0, 1, 2, 2, 3, 3, 4]
    # split halves: scale / 1.6, velocity copied from the parent
    for i, o in enumerate(owners):
        if o == 3:
            assert torch.allclose(node.gaussian_params["scales"][i], torch.full((3,), math.log(2.0 / 1.6)))
            assert torch.equal(node.gaussian_params["velocity"][i], velocity_before[3])
    # clones are exact copies of their parent
    idx = [i for i, o in enumerate(owners) if o == 0]
    assert torch.equal(node.gaussian_params["means"][idx[0]], node.gaussian_params["means"][idx[1]])
    assert torch.equal(node.gaussian_params["means"][idx[0]], means_before[0])
    # new rows have zero Adam moments
    st = opt.optimizers["toy"].state[node.gaussian_params["means"]]
    assert torch.count_nonzero(st["exp_avg"][-2:]) == 0
    # training continues on the resized parameters
    (node.gaussian_params["means"] ** 2).sum().backward()
    opt.step(2)


def test_opacity_reset_and_budget():
    node, opt = setup(4)
    strat = AbsGradStrategy(DensifyConfig(refine_start=0, refine_every=1000, reset_every=5, prune_opacity=0.005), 1.0)
    strat.step({"toy": node}, opt, 5)
    assert torch.sigmoid(node.gaussian_params["opacities"]).max() <= 0.0100001
    st = opt.optimizers["toy"].state[node.gaussian_params["opacities"]]
    assert torch.count_nonzero(st["exp_avg"]) == 0
    node, opt = setup(4)
    strat = AbsGradStrategy(DensifyConfig(refine_start=0, refine_every=1, reset_every=0, grad_threshold=0.0,
                                          max_gaussians=6), 1.0)
    strat.accumulate({"toy": node}, [NodeSlice("toy", 0, 4, None)], torch.ones(4, 2), torch.ones(4), 2, 2)
    strat.step({"toy": node}, opt, 1)
    assert node.num_gaussians <= 6 + 2  # at most `room` Gaussians selected; splits add one each


def test_accumulate_with_row_subsets():
    node, _ = setup(5)
    strat = AbsGradStrategy(DensifyConfig(), 1.0)
    rows = torch.tensor([4, 1])
    strat.accumulate({"toy": node}, [NodeSlice("toy", 0, 2, rows)], torch.tensor([[1.0, 0], [0, 2.0]]),
                     torch.tensor([1, 1]), 4, 2)
    st = strat.state["toy"]
    assert st["count"].tolist() == [0, 1, 0, 0, 1]
    assert torch.allclose(st["grad2d"], torch.tensor([0, 2.0, 0, 0, 2.0]))


def test_exponential_lr_schedule():
    assert math.isclose(exponential_lr(1e-2, 1e-4, 0, 100), 1e-2, rel_tol=1e-12)
    assert math.isclose(exponential_lr(1e-2, 1e-4, 50, 100), 1e-3, rel_tol=1e-9)
    assert math.isclose(exponential_lr(1e-2, 1e-4, 100, 100), 1e-4, rel_tol=1e-9)
    assert exponential_lr(1e-2, None, 50, 100) == 1e-2
    assert exponential_lr(1e-2, None, 5, 100, warmup_steps=10) == 5e-3


def test_no_growth_or_reset_in_the_second_half_of_a_short_run():
    node, opt = setup(4)
    strat = AbsGradStrategy(DensifyConfig(refine_start=0, refine_every=1000, reset_every=40), 1.0, max_steps=100)
    assert strat.refine_stop == 50
    before = node.gaussian_params["opacities"].detach().clone()
    strat.step({"toy": node}, opt, 80)  # would be a reset step, but growth has stopped
    assert torch.equal(node.gaussian_params["opacities"], before)
    strat.step({"toy": node}, opt, 40)
    assert torch.sigmoid(node.gaussian_params["opacities"]).max() <= 0.0100001


def test_growth_stops_at_its_fraction_of_the_schedule():
    config = DensifyConfig(grow_fraction=0.8, refine_stop=15_000)
    assert AbsGradStrategy(config, 1.0, max_steps=3000).refine_stop == 2400
    assert AbsGradStrategy(DensifyConfig(), 1.0, max_steps=3001).refine_stop == 1500
    assert AbsGradStrategy(config, 1.0, max_steps=None).refine_stop == 15_000
    with pytest.raises(ConfigError, match="grow_fraction"):
        DensifyConfig(grow_fraction=1.5)


def test_no_size_pruning_when_no_opacity_reset_happened():
    # a 3200-step run grows until 1600, so its reset at 3000 never happens: large Gaussians
    # (the sky and far surfaces of a method without a sky node) must survive step 3100
    node, opt = setup(4)
    with torch.no_grad():
        node.gaussian_params["scales"][0] = math.log(50.0)  # > prune_scale x scene radius (0.1 x 100)
    for max_steps, expected in ((3200, 4), (8000, 3)):  # 8000: a reset at 3000 during growth
        strat = AbsGradStrategy(DensifyConfig(refine_start=0, refine_every=100, reset_every=3000), 100.0,
                                max_steps=max_steps)
        strat.accumulate({"toy": node}, [NodeSlice("toy", 0, 4, None)], torch.zeros(4, 2), torch.ones(4), 2, 2)
        strat.step({"toy": node}, opt, 3100)
        assert node.num_gaussians == expected


def test_optimizer_is_fused_and_steps_like_plain_adam():
    class OneParam(Node):
        def __init__(self):
            super().__init__()
            self.gaussian_params["means"] = torch.nn.Parameter(torch.zeros(20, 3))

        def gaussian_lrs(self):
            return {"means": (0.01, None)}

    node = OneParam()
    opts = Optimizers({"n": node}, max_steps=10)
    if tuple(int(x) for x in torch.__version__.split(".")[:2]) >= (2, 4):  # CPU fused kernel since 2.4
        assert opts.optimizers["n"].defaults.get("fused") is True
    ref = torch.nn.Parameter(torch.zeros(20, 3))
    plain = torch.optim.Adam([ref], lr=0.01, eps=1e-15, foreach=False)
    g = torch.Generator().manual_seed(0)
    for step in range(5):
        grad = torch.randn(20, 3, generator=g)
        node.gaussian_params["means"].grad = grad.clone()
        ref.grad = grad.clone()
        opts.step(step)
        plain.step()
    torch.testing.assert_close(node.gaussian_params["means"].detach(), ref.detach(), rtol=1e-5, atol=1e-6)
