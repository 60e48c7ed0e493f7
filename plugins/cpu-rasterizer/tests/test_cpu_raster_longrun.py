"""A long optimisation: 2,000 Adam steps on 500 Gaussians (32x48 image) with a small
clone-and-prune densification driven by the kernel's absgrad2d. Asserts that no output,
gradient or parameter ever becomes non-finite and that the fit actually improves."""
from __future__ import annotations

import pytest
import torch

from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu.rasterizer import CpuRasterizer  # noqa: E402
from omnire_rasterizer_cpu.testing import random_scene  # noqa: E402
from omnire.camera import Camera  # noqa: E402
from omnire.rasterization import RasterSettings, Splats  # noqa: E402

W, H = 48, 32
STEPS = 2000


def target_image():
    """Checkerboard + gradient: sharp edges force densification and small scales."""
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    board = ((xx // 6 + yy // 6) % 2).float()
    return torch.stack([board, xx / W, 1 - yy / H], -1)  # (H, W, 3)


def test_two_thousand_adam_steps_with_densification():
    torch.manual_seed(0)
    sc = {k: v.float() for k, v in random_scene(500, W, H, seed=0, scale_px=2.0, depth=(1.0, 6.0)).items()}
    vm, K = sc["viewmat"], sc["K"]
    params = {
        "means": sc["means"],
        "quats": sc["quats"],
        "log_scales": sc["scales"].log(),
        "logit_opac": torch.logit(sc["opacities"]),
        "colors": sc["colors"],
    }
    lrs = {"means": 3e-3, "quats": 1e-2, "log_scales": 5e-2, "logit_opac": 1e-1, "colors": 5e-2}

    def make_opt():
        for k in params:
            params[k] = params[k].detach().clone().requires_grad_(True)
        return torch.optim.Adam([{"params": [params[k]], "lr": lrs[k]} for k in params], eps=1e-15)

    opt = make_opt()
    rast = CpuRasterizer(num_threads=1)  # tiny images: threads would only add sync cost
    target = target_image()
    bg = torch.tensor([0.0, 0.0, 0.0])
    grad_acc = torch.zeros(500)
    seen = torch.zeros(500)
    losses = []
    max_n = 0
    for step in range(STEPS):
        out = rast.rasterize(Splats(params["means"], params["quats"], params["log_scales"].exp(),
                                    torch.sigmoid(params["logit_opac"]), params["colors"]),
                             Camera.from_world_to_cam(vm, K, W, H), RasterSettings(background=bg))
        loss = (out.rgb - target).abs().mean() + 1e-3 * out.depth.mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        assert torch.isfinite(loss), step
        assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all(), step
        for k, p in params.items():
            assert torch.isfinite(p.grad).all(), (step, k)
        assert torch.isfinite(out.absgrad2d).all(), step
        opt.step()
        losses.append(float(loss.detach()))
        with torch.no_grad():
            grad_acc += out.absgrad2d.norm(dim=-1)
            seen += (out.radii > 0).float()
            if 100 <= step <= 1500 and step % 100 == 0:
                # clone the Gaussians with the largest mean absgrad, prune transparent ones;
                # optimiser state restarts (this stresses the kernel, not the strategy).
                mean_grad = grad_acc / seen.clamp_min(1)
                n = mean_grad.shape[0]
                clone = torch.topk(mean_grad, k=min(100, n)).indices
                keep = torch.sigmoid(params["logit_opac"]) > 0.01
                keep[clone] = True
                new = {}
                for k, p in params.items():
                    extra = p[clone].clone()
                    if k == "means":
                        extra = extra + 0.5 * params["log_scales"][clone].exp() * torch.randn_like(extra)
                    if k == "log_scales":
                        extra = extra - 0.5
                    new[k] = torch.cat([p[keep], extra])
                params.update(new)
                opt = make_opt()
                grad_acc = torch.zeros(params["means"].shape[0])
                seen = torch.zeros_like(grad_acc)
                max_n = max(max_n, grad_acc.shape[0])
            if step == 1000:
                # opacity reset, as in 3DGS: drives many alphas under 1/255 at once
                params["logit_opac"].clamp_(max=float(torch.logit(torch.tensor(0.01))))
    for k, p in params.items():
        assert torch.isfinite(p).all(), k
    assert max_n > 500
    first, last = sum(losses[:20]) / 20, sum(losses[-20:]) / 20
    assert last < 0.6 * first, (first, last)
