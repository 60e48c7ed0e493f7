"""The reference LiDAR renderer (``rasterize_lidar``) against a brute-force per-ray
evaluation (numpy float64), its gradients by gradcheck, known geometry (a ground plane, a
wall at a known distance), the azimuth seam, empty inputs and bad input."""
import math

import numpy as np
import pytest
import torch
from hostile import record

from omnire.api import LidarRays, LidarSettings, RasterInputError, Splats
from omnire_rasterizer_torch import TorchRasterizer
from omnire_rasterizer_torch.testing import brute_force, flat_grid, random_lidar_scene


def render(scene, rast=None, min_range=0.5, max_range=60.0, probe=None, **settings):
    rast = rast or TorchRasterizer(chunk_elements=20_000)  # small: several ray and list slices
    splats = Splats(*(scene[k] for k in ("means", "quats", "scales", "opacities", "colors")))
    rays = LidarRays(scene["pose"], scene["azimuth"], scene["elevation"], min_range, max_range, probe)
    return rast.rasterize_lidar(splats, rays, LidarSettings(**settings))


def brute(scene, min_range=0.5, max_range=60.0, eps_deg2=0.01, range_of="max_response", probe=None):
    args = [scene[k].detach().numpy() for k in ("means", "quats", "scales", "opacities", "colors", "pose",
                                                 "azimuth", "elevation")]
    return brute_force(*args, min_range, max_range, eps_deg2, range_of,
                       None if probe is None else probe.numpy())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_matches_brute_force(seed):
    scene = random_lidar_scene(300, 400, seed)
    out = render(scene)
    rng, median, feat, alpha = brute(scene)
    assert (alpha > 0.1).sum() > 50 and (alpha > 0.5).sum() > 10  # the rays see something
    np.testing.assert_allclose(out.alpha.numpy(), alpha, atol=1e-10)
    np.testing.assert_allclose(out.features.numpy(), feat, atol=1e-10)
    np.testing.assert_allclose(out.range.numpy(), rng, atol=1e-8)
    np.testing.assert_allclose(out.median_range.numpy(), median, atol=1e-8)


def test_probe_transmittance_matches_brute_force():
    """The light left at a probe range per ray: the product of (1 - alpha) over the pairs in
    front of it; 1 with the probe before every Gaussian, 1 - alpha past all of them."""
    scene = random_lidar_scene(300, 400, seed=7)
    rng = np.random.default_rng(0)
    probe = torch.tensor(rng.uniform(0.0, 25.0, 400))
    probe[:40] = -1.0  # in front of everything
    probe[40:80] = 1e3  # behind everything
    out = render(scene, probe=probe)
    _, _, _, alpha, light = brute(scene, probe=probe)
    np.testing.assert_allclose(out.probe_transmittance.numpy(), light, atol=1e-10)
    assert np.all(light[:40] == 1.0)
    np.testing.assert_allclose(light[40:80], 1.0 - alpha[40:80], atol=1e-12)
    assert 0.05 < np.mean(light[80:] < 0.5) < 0.95  # probes both in front of and behind surfaces
    assert render(scene).probe_transmittance is None


def test_gradcheck_float64():
    scene = random_lidar_scene(8, 40, seed=5)
    names = ("means", "quats", "scales", "opacities", "colors")
    g = torch.Generator().manual_seed(0)
    weights = [torch.rand(40, dtype=torch.float64, generator=g) for _ in range(3)] + [
        torch.rand(40, 2, dtype=torch.float64, generator=g)]
    # wide Gaussians so that most rays cross several (the gradients are not all zero)
    scene["scales"] = scene["scales"] * 3.0
    scene["opacities"] = scene["opacities"].clamp(max=0.8)

    def f(*leaves):
        out = render({**scene, **dict(zip(names, leaves))})
        return ((out.range * weights[0]).sum() + (out.median_range * weights[1]).sum()
                + (out.alpha * weights[2]).sum() + (out.features * weights[3]).sum())

    leaves = [scene[k].clone().requires_grad_(True) for k in names]
    f(*leaves).backward()
    for name, t in zip(names, leaves):
        assert t.grad is not None and t.grad.abs().sum() > 0, f"no gradient reaches {name}"
    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)

    probe = torch.tensor(np.random.default_rng(1).uniform(3.0, 20.0, 40))

    def light(*leaves):
        out = render({**scene, **dict(zip(names, leaves))}, probe=probe)
        return (out.probe_transmittance * weights[0]).sum()

    leaves = [scene[k].clone().requires_grad_(True) for k in names[:4]]
    light(*leaves, scene["colors"]).backward()
    assert float(leaves[3].grad.abs().sum()) > 0  # the opacities reach it
    assert torch.autograd.gradcheck(lambda *x: light(*x, scene["colors"]), leaves, eps=1e-6, atol=1e-5, rtol=1e-4,
                                    fast_mode=True)


def ground_scene(height=1.8, sigma=0.15, spacing=0.15, sector_deg=(0.0, 10.0)):
    """Flat Gaussians covering the ground plane z = 0 below a sensor at ``height`` over the
    azimuth sector (plus a margin), and a beam grid of rays looking down at it."""
    x = np.arange(0.5, 32.0, spacing)
    y = np.arange(-1.0, 7.0, spacing)
    means, quats, scales, opac = flat_grid(x, y, 0.0, sigma)
    pose = np.eye(4)
    pose[2, 3] = height
    az, el = np.meshgrid(np.arange(*sector_deg, 0.7), np.arange(-25.0, -3.0, 0.5), indexing="ij")
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    scene = dict(means=t(means), quats=t(quats), scales=t(scales), opacities=t(opac),
                 colors=t(np.ones((len(means), 1))), pose=t(pose), azimuth=t(az.ravel()), elevation=t(el.ravel()))
    truth = height / np.sin(np.radians(-el.ravel()))
    inside = truth * np.cos(np.radians(el.ravel())) < 30.0  # rays that meet the ground inside the patch
    return scene, truth, inside


def test_ground_plane_ranges_and_why_the_range_is_the_max_response():
    """Flat ground Gaussians seen at grazing angles: the distance of maximum response gives
    the ground's range to millimetres, the centre distance misses it by decimetres."""
    scene, truth, inside = ground_scene()
    out = render(scene, TorchRasterizer(), max_range=100.0)
    rng, median, _, alpha = brute(scene, max_range=100.0)
    np.testing.assert_allclose(out.median_range.numpy(), median, atol=1e-8)
    assert (out.alpha.numpy()[inside] > 0.99).all()
    err_median = np.abs(out.median_range.numpy() - truth)[inside]
    err_expected = np.abs(out.range.numpy() - truth)[inside]
    c_rng, c_median, _, _ = brute(scene, max_range=100.0, range_of="centre")
    c_err_median = np.abs(c_median - truth)[inside]
    c_err_expected = np.abs(c_rng - truth)[inside]
    print(f"ground plane, {inside.sum()} rays: median |error| max response {np.median(err_median) * 100:.2f} cm "
          f"(expected range {np.median(err_expected) * 100:.2f} cm), centre distance "
          f"{np.median(c_err_median) * 100:.2f} cm (expected {np.median(c_err_expected) * 100:.2f} cm); "
          f"95th percentiles {np.percentile(err_median, 95) * 100:.2f} / "
          f"{np.percentile(c_err_median, 95) * 100:.2f} cm")
    assert np.median(err_median) < 0.005 and np.median(err_expected) < 0.005
    assert np.percentile(err_median, 95) < 0.02
    assert np.median(c_err_median) > 5 * np.median(err_median)


def test_wall_at_a_known_distance():
    """A wall of flat Gaussians at x = 10 m (y in [-2, 2], z in [-1, 1]) seen from a sensor
    turned so that the wall straddles its azimuth 0 (rays at -10 to 30 degrees): the rays that meet
    it return range 10 / (cos e cos a); the others return nothing."""
    y, z = np.arange(-2.0, 2.01, 0.1), np.arange(-1.0, 1.01, 0.1)
    Y, Z = np.meshgrid(y, z, indexing="ij")
    means = np.stack([np.full(Y.size, 10.0), Y.ravel(), Z.ravel()], -1)
    quats = np.tile([math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0], (len(means), 1))  # normal along x
    scales = np.tile([0.1, 0.1, 1e-3], (len(means), 1))
    yaw = math.radians(-10.0)
    pose = np.eye(4)  # the sensor turned by -10 degrees: the wall spans its azimuths -1 to 21
    pose[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    world_az, el = np.meshgrid(np.arange(-20.0, 20.0, 0.9), np.arange(-12.0, 12.0, 0.7), indexing="ij")
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    scene = dict(means=t(means), quats=t(quats), scales=t(scales), opacities=t(np.full(len(means), 0.9)),
                 colors=t(np.ones((len(means), 1))), pose=t(pose), azimuth=t(world_az.ravel() + 10.0),
                 elevation=t(el.ravel()))
    out = render(scene)
    a, e = np.radians(world_az.ravel()), np.radians(el.ravel())
    truth = 10.0 / (np.cos(e) * np.cos(a))
    hit_y, hit_z = truth * np.cos(e) * np.sin(a), truth * np.sin(e)
    inside = (np.abs(hit_y) < 1.7) & (np.abs(hit_z) < 0.7)
    outside = (np.abs(hit_y) > 2.6) | (np.abs(hit_z) > 1.6)
    assert inside.sum() > 50 and outside.sum() > 50
    np.testing.assert_allclose(out.median_range.numpy()[inside], truth[inside], atol=0.005)
    np.testing.assert_allclose(out.range.numpy()[inside], truth[inside], atol=0.005)
    assert (out.alpha.numpy()[inside] > 0.99).all()
    assert (out.alpha.numpy()[outside] == 0).all() and (out.median_range.numpy()[outside] == 60.0).all()


def test_azimuth_seam():
    """A Gaussian straddling azimuth 0/360 is drawn on both sides: the same world rays give
    the same returns whether the sensor's seam cuts the Gaussian or not."""
    scene = random_lidar_scene(150, 300, seed=7)
    out = render(scene)
    yaw = math.radians(137.0)
    turn = torch.tensor([[math.cos(yaw), -math.sin(yaw), 0, 0], [math.sin(yaw), math.cos(yaw), 0, 0], [0, 0, 1, 0],
                         [0, 0, 0, 1]], dtype=torch.float64)
    turned = render({**scene, "pose": scene["pose"] @ turn, "azimuth": scene["azimuth"] - 137.0})
    near_seam = torch.remainder(scene["azimuth"] + 5.0, 360.0) < 10.0
    assert float(out.alpha[near_seam].max()) > 0.3  # rays around the seam see Gaussians
    for name in ("range", "median_range", "features", "alpha"):
        torch.testing.assert_close(getattr(turned, name), getattr(out, name), atol=1e-9, rtol=1e-9)
    rng, median, feat, alpha = brute(scene)
    np.testing.assert_allclose(out.alpha.numpy(), alpha, atol=1e-10)


def test_empty_rays_and_no_gaussians():
    scene = random_lidar_scene(20, 10, seed=1)
    leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items() if k in ("means", "opacities", "colors")}
    out = render({**scene, **leaves, "azimuth": scene["azimuth"][:0], "elevation": scene["elevation"][:0]})
    assert out.range.shape == (0,) and out.median_range.shape == (0,) and out.features.shape == (0, 2)
    (out.range.sum() + out.features.sum() + out.alpha.sum()).backward()
    assert all(float(t.grad.abs().sum()) == 0 for t in leaves.values())
    empty = {k: v[:0] for k, v in scene.items() if k in ("means", "quats", "scales", "opacities", "colors")}
    out = render({**scene, **empty}, max_range=80.0)
    assert torch.equal(out.alpha, torch.zeros(10, dtype=torch.float64))
    assert torch.equal(out.range, torch.zeros(10, dtype=torch.float64))
    assert torch.equal(out.median_range, torch.full((10,), 80.0, dtype=torch.float64))


def bad_inputs(scene):
    """(case, scene changes, range limits, the name the error must carry)."""
    nan_means = scene["means"].clone()
    nan_means[3, 1] = float("nan")
    inf_az = scene["azimuth"].clone()
    inf_az[2] = float("inf")
    return [
        ("non-finite means", {"means": nan_means}, (0.5, 60.0), "means: 1 non-finite"),
        ("non-finite azimuth", {"azimuth": inf_az}, (0.5, 60.0), "azimuth_deg: 1 non-finite"),
        ("elevation of another length", {"elevation": scene["elevation"][:-1]}, (0.5, 60.0), "elevation_deg: shape"),
        ("pose of the wrong shape", {"pose": scene["pose"][:3]}, (0.5, 60.0), "sensor_to_world: shape (3, 4)"),
        ("features without a channel axis", {"colors": scene["colors"][:, 0]}, (0.5, 60.0), "colors: shape"),
        ("elevation at the pole", {"elevation": scene["elevation"] * 0 + 90.0}, (0.5, 60.0), "elevation_deg"),
        ("integer azimuths", {"azimuth": scene["azimuth"].long()}, (0.5, 60.0), "azimuth_deg: dtype"),
        ("negative scales", {"scales": -scene["scales"]}, (0.5, 60.0), "scales: negative"),
        ("max_range below min_range", {}, (5.0, 1.0), "min_range, max_range"),
        ("infinite max_range", {}, (0.0, float("inf")), "min_range, max_range"),
        ("probes of another length", {"probe": torch.ones(5, dtype=torch.float64)}, (0.5, 60.0), "probe_range: shape"),
        ("a NaN probe", {"probe": torch.tensor([1.0, 2, float("nan"), 3, 4, 5], dtype=torch.float64)}, (0.5, 60.0),
         "probe_range: 1 non-finite"),
    ]


@pytest.mark.parametrize("case", range(12))
def test_bad_input_names_the_tensor(case):
    scene = random_lidar_scene(8, 6, seed=2)
    name, change, (lo, hi), needle = bad_inputs(scene)[case]
    probe = change.pop("probe", None)
    try:
        render({**scene, **change}, min_range=lo, max_range=hi, probe=probe)
        outcome, wrong = "rendered", True
    except RasterInputError as exc:
        outcome, wrong = str(exc), needle not in str(exc)
    record("rasterize_lidar", name, exit=2 if not wrong else 0, wrong=wrong)
    assert not wrong, f"{name}: {outcome!r} does not name {needle!r}"
    with pytest.raises(RasterInputError, match="eps_deg2"):
        render(scene, eps_deg2=float("nan"))
