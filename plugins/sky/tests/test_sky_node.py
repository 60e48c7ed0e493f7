"""Sky node: directions map to the right texels, gradients reach the map, compositing, and
a subset of the pixels gets the full image's values."""

import math

import torch

from omnire.api import Camera, ImageCache, NodeContext, SceneTime
from omnire_sky.node import SkyConfig, SkyNode, equirect_coordinates

from scene_helpers import LOOK_X, make_tiny_scene


def test_view_directions_brute_force():
    K = torch.tensor([[30.0, 0, 20], [0, 25.0, 10], [0, 0, 1]], dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.as_tensor(LOOK_X)
    d = Camera(K, c2w, 40, 20).pixel_directions()
    for v, u in [(0, 0), (7, 33), (19, 39)]:
        ray = torch.tensor([(u + 0.5 - 20) / 30, (v + 0.5 - 10) / 25, 1.0], dtype=torch.float64)
        ray = c2w[:3, :3] @ ray
        torch.testing.assert_close(d[v, u], ray / ray.norm())


def test_environment_lookup_and_gradient(tmp_path):
    scene = make_tiny_scene(tmp_path)
    ctx = NodeContext(scene, ImageCache(), 1.0, torch.device("cpu"), torch.Generator(), [])
    sky = SkyNode(SkyConfig(height=32, width=64), ctx)
    with torch.no_grad():
        sky.env[:, :, :16] = torch.tensor([0.1, 0.2, 0.9])[None, :, None, None]  # upper half blue
        sky.env[:, :, 16:] = torch.tensor([0.3, 0.3, 0.3])[None, :, None, None]
    K = torch.tensor([[20.0, 0, 24], [0, 20.0, 16], [0, 0, 1]])
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.as_tensor(LOOK_X, dtype=torch.float32)
    img = sky.render_environment(Camera(K, c2w, 48, 32), SceneTime(0, 0.0))
    assert img.shape == (32, 48, 3)
    torch.testing.assert_close(img[2, 24], torch.tensor([0.1, 0.2, 0.9]))  # looking up: sky colour
    torch.testing.assert_close(img[30, 24], torch.tensor([0.3, 0.3, 0.3]))  # looking down
    img.sum().backward()
    assert sky.env.grad is not None and sky.env.grad.abs().sum() > 0
    assert sky.gaussians_at(SceneTime(0, 0.0)) is None and sky.num_gaussians == 0


def test_equirect_coordinates_brute_force():
    d = torch.nn.functional.normalize(torch.randn(7, 5, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    uv = equirect_coordinates(d)
    for (i, j), (x, y, z) in zip([(i, j) for i in range(7) for j in range(5)], d.reshape(-1, 3).tolist()):
        expected = [math.atan2(y, x) / math.pi, -math.asin(z) / (math.pi / 2)]
        torch.testing.assert_close(uv[i, j], torch.tensor(expected), rtol=0, atol=1e-6)


def test_pixel_subset_matches_full_image(tmp_path):
    scene = make_tiny_scene(tmp_path)
    ctx = NodeContext(scene, ImageCache(), 1.0, torch.device("cpu"), torch.Generator(), [])
    sky = SkyNode(SkyConfig(height=32, width=64), ctx)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        sky.env.copy_(torch.rand(sky.env.shape, generator=g))
    K = torch.tensor([[20.0, 0, 24], [0, 20.0, 16], [0, 0, 1]])
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.as_tensor(LOOK_X, dtype=torch.float32)
    cam, t = Camera(K, c2w, 48, 32), SceneTime(0, 0.0)
    pixels = torch.randperm(48 * 32, generator=g)[:300]
    torch.testing.assert_close(cam.pixel_directions(pixels), cam.pixel_directions().reshape(-1, 3)[pixels],
                               rtol=0, atol=1e-7)
    part = sky.render_environment(cam, t, pixels)
    assert part.shape == (300, 3)
    torch.testing.assert_close(part, sky.render_environment(cam, t).reshape(-1, 3)[pixels], rtol=0, atol=1e-6)
