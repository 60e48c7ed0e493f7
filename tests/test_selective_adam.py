"""Selective Adam against torch.optim.Adam: identical on the rows it touches, nothing
changes elsewhere, and absent nodes cost nothing."""
import torch

from omnire.nodes.base import Node, ParamGroup
from omnire.optim import Optimizers, selective_adam_step


def adam_group(lr=0.01):
    return {"lr": lr, "betas": (0.9, 0.999), "eps": 1e-15, "weight_decay": 0, "amsgrad": False, "maximize": False}


def test_all_rows_equals_torch_adam_over_many_steps():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(50, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = a.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([a], lr=0.01, eps=1e-15)
    state: dict = {}
    rows = torch.arange(50)
    for _ in range(20):
        grad = torch.randn(50, 3, generator=g, dtype=torch.float64)
        a.grad = grad.clone()
        opt.step()
        b.grad = grad.clone()
        selective_adam_step(b, rows, state, adam_group())
    torch.testing.assert_close(b, a, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(state["exp_avg_sq"], opt.state[a]["exp_avg_sq"], rtol=1e-12, atol=0)


def test_subset_updates_those_rows_as_adam_and_leaves_the_rest():
    g = torch.Generator().manual_seed(1)
    p = torch.randn(40, 2, generator=g, dtype=torch.float64, requires_grad=True)
    before = p.detach().clone()
    rows = torch.tensor([3, 7, 8, 30])
    ref = before[rows].clone().requires_grad_(True)
    opt = torch.optim.Adam([ref], lr=0.05, eps=1e-15)
    state: dict = {}
    for _ in range(5):
        grad = torch.randn(40, 2, generator=g, dtype=torch.float64)
        p.grad = grad.clone()
        selective_adam_step(p, rows, state, adam_group(0.05))
        ref.grad = grad[rows].clone()
        opt.step()
    torch.testing.assert_close(p.detach()[rows], ref.detach(), rtol=1e-12, atol=1e-12)
    others = torch.ones(40, dtype=torch.bool)
    others[rows] = False
    assert torch.equal(p.detach()[others], before[others])
    assert not bool(state["exp_avg"][others].any())


class TwoGroupNode(Node):
    def __init__(self):
        super().__init__()
        self.gaussian_params["means"] = torch.nn.Parameter(torch.zeros(10, 3))
        self.extra = torch.nn.Parameter(torch.zeros(2))

    def param_groups(self):
        return [ParamGroup("means", [self.gaussian_params["means"]], 0.1, key="means"),
                ParamGroup("extra", [self.extra], 0.1)]


def test_optimizers_step_uses_rendered_rows_for_per_gaussian_groups_only():
    node = TwoGroupNode()
    opts = Optimizers({"n": node}, max_steps=10)
    node.gaussian_params["means"].grad = torch.ones(10, 3)
    node.extra.grad = torch.ones(2)
    opts.step(0, {"n": torch.tensor([1, 4])})
    moved = (node.gaussian_params["means"].detach() != 0).any(dim=1)
    assert moved.nonzero().flatten().tolist() == [1, 4]
    assert bool((node.extra.detach() != 0).all())  # non-Gaussian groups: ordinary Adam
    # Checkpoint round trip keeps the selective state in torch's layout.
    state = opts.state_dict()
    fresh = Optimizers({"n": node}, max_steps=10)
    fresh.load_state_dict(state)
    # Dense step afterwards (rows None) continues from that state without error.
    node.gaussian_params["means"].grad = torch.ones(10, 3)
    fresh.step(1, {"n": None})
    assert bool((node.gaussian_params["means"].detach() != 0).all())
