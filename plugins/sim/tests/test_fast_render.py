"""The scene model's inference path (SceneModel.render without autograd: raw node outputs
straight into the native rasterizer) gives the training path's pixels (autograd on:
frustum culling, concatenation, torch SH and activations, then the rasterizer), and the sky
only where the Gaussians let it show."""
from __future__ import annotations

import numpy as np
import torch

from omnire.api import View
from omnire.model import ENVIRONMENT_MIN_TRANSMITTANCE
from sim_scene import build, street_scene


def test_fast_path_equals_training_path(tmp_path, plugins):
    recon = build(street_scene(tmp_path / "s"), seed=1, plugins=plugins)
    g = torch.Generator().manual_seed(0)
    for node in recon.model.gaussian_nodes().values():  # view-dependent colour, so SH is exercised
        shN = node.gaussian_params["shN"]
        with torch.no_grad():
            shN.copy_(0.3 * torch.randn(shN.shape, generator=g))
    recon.model.use_fused_training = False  # the reference: the plain torch composition
    assert recon.model.fast_inference() is False  # autograd is on here
    for view in recon.scene.views(np.array([0, 3, 7])):
        cam, t = recon.camera(view).resized(120, 80), recon.time(view.frame)
        for degree, hidden in ((3, frozenset()), (1, frozenset({"sky"})), (0, frozenset({"background"}))):
            train = recon.render(cam, t, sh_degree=degree, hidden=hidden)
            with torch.no_grad():
                assert recon.model.fast_inference()
                fast = recon.render(cam, t, sh_degree=degree, hidden=hidden)
            assert float(train.alpha.detach().max()) > 0.5
            # The inference path draws actors box-local, through the camera composed with their
            # box poses; the torch composition draws world copies. Float rounding can flip
            # whether a pixel takes one more Gaussian at the alpha or transmittance threshold (a
            # change of at most that Gaussian's weight): a pixel or two may differ more.
            # and without autograd the sky is left out where the Gaussians leave a transmittance
            # of at most ENVIRONMENT_MIN_TRANSMITTANCE (test_sky_skipped_where_covered)
            for key in ("rgb", "alpha"):
                diff = (getattr(fast, key) - getattr(train, key).detach()).abs()
                tol = 1e-4 + (ENVIRONMENT_MIN_TRANSMITTANCE if key == "rgb" and "sky" not in hidden else 0.0)
                assert int((diff > tol).any(-1).sum()) <= 2 and float(diff.max()) <= 1e-2, (view, degree, key)
            depth_diff = (fast.depth - train.depth.detach()).abs()[train.alpha.detach() > 0.01]
            assert int((depth_diff > 1e-4 * float(train.depth.detach().max())).sum()) <= 2
    # nothing drawn at all: background only, same as the training path
    cam = recon.camera(View(0, 0))
    with torch.no_grad():
        fast = recon.render(cam, recon.time(0), hidden=frozenset(recon.model.nodes))
    assert torch.equal(fast.rgb, recon.render(cam, recon.time(0), hidden=frozenset(recon.model.nodes)).rgb)


def test_sky_skipped_where_covered(tmp_path, plugins):
    """Without autograd the sky is evaluated only at pixels whose transmittance T exceeds
    ENVIRONMENT_MIN_TRANSMITTANCE: the image stays within that (< 1/255) of the full-sky
    composite C_gs + T C_sky computed in float64 (the reference), the evaluated pixels keep
    its values, and the render reports how many it evaluated. With autograd every pixel is."""
    recon = build(street_scene(tmp_path / "s"), seed=2, plugins=plugins)
    recon.model.exposure = None  # the reference composites the sky alone
    background = torch.tensor(recon.model.method.background_color, dtype=torch.float64)  # drawn without the sky
    g = torch.Generator().manual_seed(0)
    sky = recon.model.nodes["sky"]
    with torch.no_grad():
        sky.env.copy_(torch.rand(sky.env.shape, generator=g))  # a sky that shows where it is drawn
        for node in recon.model.gaussian_nodes().values():  # opaque enough to cover some pixels
            node.gaussian_params["opacities"].add_(6.0)
    skipped_any = False
    for view in recon.scene.views(np.array([0, 5])):
        cam, t = recon.camera(view).resized(120, 80), recon.time(view.frame)
        with torch.no_grad():
            fast = recon.render(cam, t)
            gaussians = recon.render(cam, t, hidden=frozenset({"sky"}))
            T = 1.0 - gaussians.alpha.double()
            reference = gaussians.rgb.double() + T * (sky.render_environment(cam, t).double() - background)
        shown = T[..., 0] > ENVIRONMENT_MIN_TRANSMITTANCE
        assert fast.environment_pixels == int(shown.sum()), view
        skipped_any |= 0 < fast.environment_pixels < cam.width * cam.height
        diff = (fast.rgb.double() - reference).abs()
        assert float(diff[shown].max()) <= 1e-6, view
        assert float(diff.max()) <= ENVIRONMENT_MIN_TRANSMITTANCE + 1e-6 < 1 / 255, view
        assert recon.render(cam, t).environment_pixels == cam.width * cam.height  # autograd on: all
        with torch.no_grad():
            assert recon.render(cam, t, hidden=frozenset({"sky"})).environment_pixels == 0
    assert skipped_any
