"""Coarse-to-fine training (omnire/resolution.py): camera, image, mask and LiDAR downscaling
against brute force, and a training step at half resolution compared with its parts."""
import numpy as np
import pytest
import torch

from omnire.camera import Camera
from omnire.observations import Observations
from omnire.plugins import load_plugins
from omnire.resolution import downscale_factor, downscale_image, downscale_pixel_samples
from omnire.trainer import TrainConfig, Trainer, TrainerConfig


def test_schedule_halves_the_factor_every_level():
    got = [downscale_factor(s, 2, 100) for s in (0, 99, 100, 199, 200, 5000)]
    assert got == [4, 4, 2, 2, 1, 1]
    assert downscale_factor(0, 0, 100) == 1 and downscale_factor(0, 3, 0) == 1


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_downscaled_camera_pixel_is_the_block_of_full_resolution_pixels(factor):
    """A world point projected by the downscaled camera lands in block floor(u_full / f)."""
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[300.0, 0, 241.3], [0, 310.0, 133.7], [0, 0, 1]])
    c2w = torch.eye(4)
    cam = Camera(K, c2w, 480, 270)
    small = cam.downscaled(factor)
    assert (small.width, small.height) == (480 // factor, 270 // factor)
    pts = torch.cat([torch.rand(200, 2, generator=g) * 8 - 4, torch.rand(200, 1, generator=g) * 20 + 2], 1)

    def project(c):
        uv = pts[:, :2] / pts[:, 2:] @ c.K[:2, :2].T + c.K[:2, 2]
        return uv.double()

    full, low = project(cam), project(small)
    assert torch.allclose(low, full / factor, atol=1e-4)
    inside = (full[:, 0] < small.width * factor) & (full[:, 1] < small.height * factor) & (full >= 0).all(1)
    assert torch.equal(torch.floor(low[inside]).long(), torch.div(torch.floor(full[inside]).long(), factor,
                                                                  rounding_mode="floor"))


@pytest.mark.parametrize("factor", [2, 3])
def test_downscale_image_is_block_mean(factor):
    img = torch.rand(11, 14, 3, generator=torch.Generator().manual_seed(1))
    out = downscale_image(img, factor)
    H, W = 11 // factor, 14 // factor
    assert out.shape == (H, W, 3)
    for y in range(H):
        for x in range(W):
            block = img[y * factor:(y + 1) * factor, x * factor:(x + 1) * factor].reshape(-1, 3)
            assert torch.allclose(out[y, x], block.mean(0), atol=1e-6)


def test_downscale_pixel_samples_against_brute_force():
    rng = np.random.default_rng(2)
    W, H, f = 23, 17, 3
    pixels = torch.from_numpy(rng.choice(W * H, 120, replace=False))
    depth = torch.from_numpy(rng.uniform(1, 50, 120)).float()
    depth[5] = depth[6]  # a tie: the first sample of the pair wins, whatever the block
    idx, z = downscale_pixel_samples(pixels, depth, W, H, f)
    expected: dict[int, float] = {}
    for p, d in zip(pixels.tolist(), depth.tolist()):
        u, v = p % W // f, p // W // f
        if u >= W // f or v >= H // f:
            continue
        key = v * (W // f) + u
        if key not in expected or d < expected[key]:
            expected[key] = d
    assert idx.tolist() == sorted(expected)
    assert z.tolist() == [expected[k] for k in sorted(expected)]


def test_observations_at_half_resolution(tiny_scene):
    obs = Observations(tiny_scene, torch.device("cpu"))
    view = tiny_scene.views(tiny_scene.train_frames)[1]
    full, half = obs.image(view), obs.image(view, 2)
    assert half.shape == (full.shape[0] // 2, full.shape[1] // 2, 3)
    assert torch.allclose(half, downscale_image(full, 2))
    assert obs.image(view, 2) is half  # cached
    lidar_full, lidar_half = obs.lidar(view), obs.lidar(view, 2)
    assert lidar_full is not None and 0 < lidar_half[0].numel() <= lidar_full[0].numel()
    assert int(lidar_half[0].max()) < half.shape[0] * half.shape[1]
    mask = obs.dynamic_mask(view, "all", 2)
    assert mask.shape[:2] == half.shape[:2] and float(mask.min()) >= 0 and float(mask.max()) <= 1


def test_training_step_at_half_resolution_compares_half_resolution_images(tiny_scene, tmp_path):
    """The step's PSNR is the one of the downscaled render against the block-mean target, and
    the schedule reaches full resolution at ``resolution_schedule`` steps."""
    plugins = load_plugins()
    cfg = plugins.methods.get("3dgs").config_factory()
    cfg.num_downscales, cfg.resolution_schedule = 1, 2
    tc = TrainerConfig(max_steps=4, output_dir=tmp_path, run_name="r", progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig("3dgs", "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    view = trainer.train_views[0]
    assert trainer.resolution_factor() == 2
    with torch.no_grad():
        cam = trainer.recon.camera(view).downscaled(2)
        rgb = trainer.recon.render(cam, trainer.recon.time(view.frame), step=0).rgb.clamp(0, 1)
        target = trainer.observations.image(view, 2)
        expected = float(-10 * torch.log10(((rgb - target) ** 2).mean()))
    assert rgb.shape == target.shape == (tiny_scene.cameras[0].height // 2, tiny_scene.cameras[0].width // 2, 3)
    stats = trainer.train_step(view)
    assert stats["psnr"] == pytest.approx(expected, abs=1e-4)
    trainer.train_step(view)
    assert trainer.resolution_factor() == 1
    stats = trainer.train_step(view)
    assert np.isfinite(stats["loss"])
