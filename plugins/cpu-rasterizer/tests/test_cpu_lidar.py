"""The native LiDAR kernels (csrc/lidar.cpp) against the torch reference: forward and every
gradient in float64 (to rounding) and float32 (tolerances below), a float64 gradcheck of
the native path, beam-grid rays and recorded directions, thread counts, empty inputs.

float32 tolerances, against the float64 reference on the same scene: alpha and features
2e-4 absolute, ranges 1e-3 relative (the angles are float32: 3e-5 degrees at 360), and the
gradients 2e-3 of the largest gradient of each tensor."""
import numpy as np
import pytest
import torch

from omnire.api import BeamModel, LidarRays, LidarSettings, Splats
from omnire_rasterizer_cpu._build import LIDAR_EXTENSION
from omnire_rasterizer_torch import TorchRasterizer
from omnire_rasterizer_torch.testing import random_lidar_scene

OK, REASON = LIDAR_EXTENSION.load()
if OK is None:
    pytest.skip(f"cpu LiDAR extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu.rasterizer import CpuRasterizer  # noqa: E402

NAMES = ("means", "quats", "scales", "opacities", "colors")
OUTPUTS = ("range", "median_range", "alpha", "features")


def run(rast, scene, rays=None, dtype=torch.float64, weights=None):
    """Render ``scene`` with ``rast`` in ``dtype``; backward a weighted sum of every output
    (the transmittance at the probes too when the rays have them). Returns the outputs
    (float64) and the gradients of the five splat tensors (float64)."""
    leaves = [scene[k].detach().to(dtype).clone().requires_grad_(True) for k in NAMES]
    if rays is None:
        rays = LidarRays(scene["pose"], scene["azimuth"], scene["elevation"], 0.5, 60.0)
    out = rast.rasterize_lidar(Splats(*leaves), rays, LidarSettings())
    outs = [getattr(out, k) for k in OUTPUTS]
    assert (out.probe_transmittance is None) == (rays.probe_range is None)
    if rays.probe_range is not None:
        outs.append(out.probe_transmittance)
    if weights is None:
        g = torch.Generator().manual_seed(3)
        weights = [torch.rand(o.shape, generator=g, dtype=torch.float64) for o in outs]
    sum((o * w.to(o.dtype)).sum() for o, w in zip(outs, weights)).backward()
    return [o.detach().double() for o in outs], [t.grad.double() for t in leaves]


@pytest.mark.parametrize("seed", [0, 1])
def test_float64_forward_and_gradients_equal_the_reference(seed):
    scene = random_lidar_scene(1500, 2000, seed)
    outs, grads = run(CpuRasterizer(), scene)
    ref_outs, ref_grads = run(TorchRasterizer(), scene)
    assert (ref_outs[2] > 0.5).sum() > 100
    for name, a, b in zip(OUTPUTS, outs, ref_outs):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-9, msg=f"output {name}")
    for name, a, b in zip(NAMES, grads, ref_grads):
        assert b.abs().max() > 0, name
        torch.testing.assert_close(a, b, atol=1e-9 * float(b.abs().max()), rtol=1e-7, msg=f"gradient of {name}")


def probed(scene, seed):
    """The scene's rays with probe ranges spread over its Gaussians' distances (3-20 m)."""
    probe = torch.tensor(np.random.default_rng(seed).uniform(2.0, 22.0, len(scene["azimuth"])))
    return LidarRays(scene["pose"], scene["azimuth"], scene["elevation"], 0.5, 60.0, probe)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_probe_transmittance_and_its_gradient_equal_the_reference(dtype):
    scene = random_lidar_scene(1500, 2000, seed=8)
    rays = probed(scene, 0)
    outs, grads = run(CpuRasterizer(), scene, rays, dtype=dtype)
    ref_outs, ref_grads = run(TorchRasterizer(), scene, rays)
    light, ref_light = outs[-1], ref_outs[-1]
    assert 0.1 < float((ref_light < 0.5).double().mean()) < 0.9
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    torch.testing.assert_close(light, ref_light, atol=tol, rtol=0)
    for name, a, b in zip(NAMES, grads, ref_grads):
        scale = float(b.abs().max())
        assert float((a - b).abs().max()) <= (1e-9 if dtype == torch.float64 else 2e-3) * scale, name


def test_float32_against_the_float64_reference():
    scene = random_lidar_scene(1500, 2000, seed=4)
    outs, grads = run(CpuRasterizer(), scene, dtype=torch.float32)
    ref_outs, ref_grads = run(TorchRasterizer(), scene)
    for name, a, b in zip(OUTPUTS, outs, ref_outs):
        if name in ("range", "median_range"):
            hit = ref_outs[2] > 0.05  # where something is composited (a range of nothing is 0 or max_range)
            np.testing.assert_allclose(a[hit], b[hit], rtol=1e-3, err_msg=name)
        else:
            np.testing.assert_allclose(a, b, atol=2e-4, err_msg=name)
    for name, a, b in zip(NAMES, grads, ref_grads):
        scale = float(b.abs().max())
        worst = float((a - b).abs().max())
        assert worst <= 2e-3 * scale, f"gradient of {name}: off by {worst:.3g} of {scale:.3g}"


def test_gradcheck_native_float64():
    scene = random_lidar_scene(8, 40, seed=5)
    scene["scales"] = scene["scales"] * 3.0  # most rays cross several Gaussians
    scene["opacities"] = scene["opacities"].clamp(max=0.8)
    g = torch.Generator().manual_seed(0)
    weights = [torch.rand(40, dtype=torch.float64, generator=g) for _ in range(3)] + [
        torch.rand(40, 2, dtype=torch.float64, generator=g)]
    rays = LidarRays(scene["pose"], scene["azimuth"], scene["elevation"], 0.5, 60.0)
    rast = CpuRasterizer()

    def f(*leaves):
        out = rast.rasterize_lidar(Splats(*leaves), rays)
        return sum((getattr(out, k) * w).sum() for k, w in zip(OUTPUTS, weights))

    leaves = [scene[k].clone().requires_grad_(True) for k in NAMES]
    f(*leaves).backward()
    assert all(float(t.grad.abs().sum()) > 0 for t in leaves)  # every input takes part
    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-5, rtol=1e-4)  # every input element

    rays = probed(scene, 1)

    def light(*leaves):
        out = rast.rasterize_lidar(Splats(*leaves, scene["colors"]), rays)
        return (out.probe_transmittance * weights[0]).sum() + (out.alpha * weights[1]).sum()

    leaves = [scene[k].clone().requires_grad_(True) for k in NAMES[:4]]
    assert torch.autograd.gradcheck(light, leaves, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_beam_grid_and_recorded_directions_and_threads():
    """A BeamModel's grid (rays on a grid) and scattered directions (recorded returns) give
    the reference's numbers; 1 and 2 threads give the same."""
    scene = random_lidar_scene(800, 10, seed=6)
    model = BeamModel(np.linspace(-20.0, 20.0, 16), azimuth_resolution_deg=1.5, max_range=60.0, min_range=0.5)
    grid = LidarRays.from_beam_model(scene["pose"], model)
    assert len(grid) == 16 * 240
    outs, grads = run(CpuRasterizer(num_threads=2), scene, grid)
    ref_outs, ref_grads = run(TorchRasterizer(), scene, grid)
    for a, b in zip(outs + grads, ref_outs + ref_grads):
        torch.testing.assert_close(a, b, atol=1e-9 * max(1.0, float(b.abs().max())), rtol=1e-7)
    one = run(CpuRasterizer(num_threads=1), scene, grid)
    for a, b in zip(outs + grads, one[0] + one[1]):
        torch.testing.assert_close(a, b, atol=1e-12 * max(1.0, float(b.abs().max())), rtol=1e-10)


def test_empty_rays_and_no_gaussians():
    scene = random_lidar_scene(20, 10, seed=1)
    rast = CpuRasterizer()
    no_rays = LidarRays(scene["pose"], scene["azimuth"][:0], scene["elevation"][:0], 0.5, 60.0)
    outs, grads = run(rast, scene, no_rays)
    assert outs[0].shape == (0,) and outs[3].shape == (0, 2)
    assert all(float(g.abs().sum()) == 0 for g in grads)
    empty = {**scene, **{k: scene[k][:0] for k in NAMES}}
    outs, _ = run(rast, empty)
    assert torch.equal(outs[2], torch.zeros(10, dtype=torch.float64))
    assert torch.equal(outs[1], torch.full((10,), 60.0, dtype=torch.float64))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_gaussians_stay_finite_and_agree(dtype):
    """Zero and huge scales, zero and unnormalised quaternions, Gaussians at the sensor, on
    its vertical axis, beyond the range limits, needles along a ray and opacities at the
    threshold: outputs and gradients finite, native equal to the reference in float64 (in
    float32 a needle's range, a ratio of terms 10^8 apart, is too ill conditioned to
    compare)."""
    means = torch.tensor([[5.0, 0, 0], [0, 0, 0], [0, 0, 3], [0.001, 0, 4], [100, 0, 0], [5, 1, 0], [4, 0, 0.1],
                          [6, -0.2, 0], [3, 3, 0], [5, 0.5, 0.2]], dtype=dtype)
    quats = torch.tensor([[0.0, 0, 0, 0], [5, 0, 0, 0], [1, 1, 1, 1], [1, 0, 0, 0], [1, 0, 0, 0], [1e-30, 0, 0, 0],
                          [1, 0, 0, 0], [0.7, 0, 0.7, 0], [1, 2, 3, 4], [0, 0, 0, 1]], dtype=dtype)
    scales = torch.tensor([[0.0, 0, 0], [1, 1, 1], [1, 1, 1], [1, 1, 1], [1e4, 1e4, 1e4], [1e-3, 2, 0],
                           [3.0, 1e-6, 1e-6], [0.5, 0.5, 1e-9], [0.2, 0.2, 0.2], [1e2, 1e-2, 1e-2]], dtype=dtype)
    opac = torch.tensor([0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 1.0 / 255.0, 0.99], dtype=dtype)
    colors = torch.rand(10, 2, dtype=dtype, generator=torch.Generator().manual_seed(0))
    az = torch.tensor([0.0, 359.99, 0.01, 1.0, 5.0, 10.0, 45.0, 180.0, 300.0, -0.5], dtype=dtype)
    el = torch.tensor([0.0, 0.0, 1.0, -1.0, 2.0, 89.9, -89.9, 0.0, 0.0, 5.0], dtype=dtype)
    rays = LidarRays(torch.eye(4, dtype=dtype), az, el, 0.0, 200.0)
    outs = {}
    for rast in (CpuRasterizer(), TorchRasterizer()):
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
        out = rast.rasterize_lidar(Splats(*leaves), rays)
        (out.range.sum() + out.median_range.sum() + out.alpha.sum() + out.features.sum()).backward()
        for t in [out.range, out.median_range, out.alpha, out.features, *[p.grad for p in leaves]]:
            assert torch.isfinite(t).all(), rast.name
        assert float(out.alpha.detach().max()) > 0.5
        outs[rast.name] = [out.range, out.median_range, out.alpha, out.features, *[p.grad for p in leaves]]
    if dtype == torch.float64:
        for a, b in zip(outs["cpu"], outs["torch"]):
            torch.testing.assert_close(a.detach(), b.detach(), atol=1e-9, rtol=1e-7)
