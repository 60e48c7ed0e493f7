"""Camera-pose refinement (omnire/camerapose.py): the world transform against moving the
camera itself (points in float64, a real render), its gradient against finite differences,
what a training step learns, and its place in checkpoints."""
import dataclasses

import numpy as np
import torch

from omnire.camera import Camera
from omnire.camerapose import CameraPoseRefinement
from omnire.data.scene import SceneTime
from omnire.plugins import load_plugins
from omnire.trainer import TrainConfig, Trainer, TrainerConfig


def make(dtype=torch.float32, scale=0.05):
    ref = CameraPoseRefinement(["front", "left"], 6, np.array([0, 2, 3, 5]), 1e-4, torch.device("cpu"))
    with torch.no_grad():
        ref.delta.data = torch.randn(12, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64).to(dtype) * scale
    return ref


def random_camera(dtype, seed=1):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(4, generator=g, dtype=torch.float64)
    q = q / q.norm()
    w, x, y, z = q
    R = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3], c2w[:3, 3] = R, torch.randn(3, generator=g, dtype=torch.float64) * 10
    K = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]], dtype=dtype)
    return Camera(K, c2w.to(dtype), 64, 48, "left")


def test_world_transform_shows_the_recorded_camera_what_the_refined_camera_sees():
    ref = make(torch.float64)
    cam = random_camera(torch.float64)
    t = SceneTime(1.0, 0.1)  # held out: interpolated between frames 0 and 2
    R, tr = ref.world_transform(cam, t)
    x = torch.randn(100, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 20
    refined = ref.refined_camera(cam, t)
    assert not torch.allclose(refined.cam_to_world, cam.cam_to_world)
    in_refined = (torch.linalg.inv(refined.cam_to_world) @ torch.cat([x, torch.ones(100, 1, dtype=x.dtype)], 1).T).T
    moved = x @ R.T + tr
    in_recorded = (torch.linalg.inv(cam.cam_to_world) @ torch.cat([moved, torch.ones(100, 1, dtype=x.dtype)], 1).T).T
    assert torch.allclose(in_refined, in_recorded, atol=1e-10)
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=R.dtype), atol=1e-12)
    # a camera the scene did not record is not moved
    other = dataclasses.replace(cam, name="")
    assert ref.world_transform(other, t) is None and ref.refined_camera(other, t) is other


def test_world_transform_gradient_matches_finite_differences():
    cam = random_camera(torch.float64)
    x = torch.randn(5, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 5
    probe = torch.randn(5, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    ref = CameraPoseRefinement(["left"], 1, np.array([0]), 1e-4, torch.device("cpu"))
    ref.delta.data = ref.delta.data.double()

    def f() -> torch.Tensor:
        R, tr = ref.world_transform(cam, SceneTime(0.0, 0.0))
        return ((x @ R.T + tr) * probe).sum()

    for start in ([0.0] * 6, [0.01, -0.02, 0.005, 0.1, -0.05, 0.2]):
        with torch.no_grad():
            ref.delta[0] = torch.tensor(start, dtype=torch.float64)
        ref.delta.grad = None
        f().backward()
        analytic = ref.delta.grad.to_dense()[0]  # row-sparse gradient (omnire/rowsparse.py)
        numeric = torch.zeros(6, dtype=torch.float64)
        for i in range(6):
            with torch.no_grad():
                ref.delta[0, i] += 1e-6
                up = f()
                ref.delta[0, i] -= 2e-6
                down = f()
                ref.delta[0, i] += 1e-6
            numeric[i] = (up - down) / 2e-6
        assert torch.allclose(analytic, numeric, rtol=1e-6, atol=1e-7)


def test_training_renders_at_the_refined_pose_and_learns_the_trained_view_only(tiny_scene, tmp_path):
    plugins = load_plugins()
    cfg = plugins.methods.get("3dgs").config_factory()
    cfg.camera_pose_refinement, cfg.exposure = True, False
    tc = TrainerConfig(max_steps=3, output_dir=tmp_path, run_name="r", progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig("3dgs", "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    poses = trainer.model.camera_poses
    view = trainer.train_views[2]
    camera, t = trainer.recon.camera(view), trainer.recon.time(view.frame)
    with torch.no_grad():
        poses.per_view[view.camera, view.frame] = torch.tensor([0.02, -0.015, 0.01, 0.2, -0.1, 0.1])
        refined = poses.refined_camera(camera, t)
        a = trainer.recon.render(camera, t, sh_degree=0).rgb  # Gaussians moved, recorded camera
        trainer.model.camera_poses = None
        b = trainer.recon.render(refined, t, sh_degree=0).rgb  # camera moved
        c = trainer.recon.render(camera, t, sh_degree=0).rgb
        trainer.model.camera_poses = poses
        poses.delta.zero_()
    # same image up to float rounding (a few pixels flip a 1/255 alpha cut-off); not the unrefined one
    assert (a - b).abs().mean() < 1e-5 and (a - b).abs().max() < 1e-2
    assert (a - c).abs().mean() > 100 * (a - b).abs().mean()
    trainer.train_step(view)
    changed = poses.per_view.detach().abs().sum(-1) > 0  # (cameras, frames)
    expected = torch.zeros_like(changed)
    expected[view.camera, view.frame] = True
    assert torch.equal(changed, expected)
    state = torch.load(trainer.save_checkpoint(), weights_only=False)
    assert torch.equal(state["model"]["camera_poses.delta"], poses.delta.detach())
    del state["model"]["camera_poses.delta"]  # as written before pose refinement existed
    trainer.recon.load_state(state)
    assert trainer.model.camera_poses is None


def test_pose_refinement_is_on_by_default_for_every_method():
    plugins = load_plugins()
    for name in plugins.methods.names():
        assert plugins.methods.get(name).config_factory().camera_pose_refinement is True
