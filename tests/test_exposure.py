"""Per-camera, per-frame exposure (omnire/exposure.py): the transform against a per-pixel
brute force, interpolation to held-out and fractional frames, what a training step learns,
and its place in checkpoints."""
import numpy as np
import pytest
import torch

from omnire.data.scene import SceneTime
from omnire.errors import ConfigError
from omnire.exposure import ExposureCompensation
from omnire.plugins import load_plugins
from omnire.trainer import TrainConfig, Trainer, TrainerConfig


def make(train_frames=(0, 2, 3, 5), num_frames=6):
    exp = ExposureCompensation(["front", "left"], num_frames, np.array(train_frames), 1e-3, torch.device("cpu"))
    with torch.no_grad():
        exp.delta.normal_(0, 0.1, generator=torch.Generator().manual_seed(0))
    return exp


def test_apply_is_the_affine_transform_per_pixel():
    exp = make()
    rgb = torch.rand(4, 5, 3, generator=torch.Generator().manual_seed(1))
    out = exp.apply(rgb, "left", SceneTime(2.0, 0.2))
    d = exp.per_view[1, 2].detach().double()
    A, b = torch.eye(3, dtype=torch.float64) + d[:, :3], d[:, 3]
    for y in range(4):
        for x in range(5):
            assert torch.allclose(out[y, x].double(), A @ rgb[y, x].double() + b, atol=1e-6)


def test_held_out_and_fractional_frames_interpolate_training_frames():
    exp = make()
    d = exp.per_view.detach()
    # frame 1 is held out, between training frames 0 and 2; frame 4 between 3 and 5
    assert torch.allclose(exp.delta_at("front", SceneTime(1.0, 0.1)), 0.5 * (d[0, 0] + d[0, 2]))
    assert torch.allclose(exp.delta_at("front", SceneTime(4.0, 0.4)), 0.5 * (d[0, 3] + d[0, 5]))
    # a moment between frames 2 and 3 blends them
    assert torch.allclose(exp.delta_at("left", SceneTime(2.25, 0.225)), 0.75 * d[1, 2] + 0.25 * d[1, 3], atol=1e-7)
    # a camera the scene did not record is not transformed
    rgb = torch.rand(2, 2, 3)
    assert exp.delta_at("", SceneTime(1.0, 0.1)) is None and exp.apply(rgb, "synthetic", SceneTime(1.0, 0.1)) is rgb


def test_training_learns_the_transform_of_the_trained_view_only(tiny_scene, tmp_path):
    plugins = load_plugins()
    cfg = plugins.methods.get("3dgs").config_factory()
    tc = TrainerConfig(max_steps=3, output_dir=tmp_path, run_name="r", progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig("3dgs", "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    exp = trainer.model.exposure
    view = trainer.train_views[2]
    with torch.no_grad():  # at identity the render is the untransformed one
        a = trainer.recon.render_view(view).rgb
        trainer.model.exposure = None
        b = trainer.recon.render_view(view).rgb
        trainer.model.exposure = exp
    assert torch.equal(a, b)
    trainer.train_step(view)
    changed = exp.per_view.detach().abs().sum((-1, -2)) > 0  # (cameras, frames)
    expected = torch.zeros_like(changed)
    expected[view.camera, view.frame] = True
    assert torch.equal(changed, expected)
    # lazy Adam: a step on another view leaves this view's transform where it was (a dense
    # step would keep moving it with the momentum of its last gradient)
    before = exp.per_view.detach().clone()
    other = next(v for v in trainer.train_views if (v.camera, v.frame) != (view.camera, view.frame))
    trainer.train_step(other)
    assert torch.equal(exp.per_view.detach()[view.camera, view.frame], before[view.camera, view.frame])
    assert not torch.equal(exp.per_view.detach()[other.camera, other.frame], before[other.camera, other.frame])
    assert "exposure.delta" in trainer.model.state_dict()
    path = trainer.save_checkpoint()
    state = torch.load(path, weights_only=False)
    assert torch.equal(state["model"]["exposure.delta"], exp.delta.detach())


def test_a_checkpoint_with_per_camera_frame_rows_loads():
    exp = make()
    old = {"delta": exp.per_view.detach().clone()}  # (C, F, 3, 4), as written before the rows were flattened
    fresh = ExposureCompensation(["front", "left"], 6, np.array((0, 2, 3, 5)), 1e-3, torch.device("cpu"))
    fresh.load_state_dict(old)
    assert torch.equal(fresh.per_view, old["delta"])


def test_exposure_is_learned_by_every_method_by_default():
    plugins = load_plugins()
    for name in plugins.methods.names():
        assert plugins.methods.get(name).config_factory().exposure is True


def test_a_checkpoint_from_before_exposure_loads_and_renders_without_it(tiny_scene, tmp_path):
    plugins = load_plugins()
    cfg = plugins.methods.get("3dgs").config_factory()
    tc = TrainerConfig(max_steps=1, output_dir=tmp_path, run_name="r", progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig("3dgs", "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    view = trainer.train_views[0]
    state = trainer.state_dict()
    with torch.no_grad():
        trainer.model.exposure.delta.fill_(0.2)
    del state["model"]["exposure.delta"]  # as written before exposure existed
    trainer.recon.load_state(state)
    assert trainer.model.exposure is None
    cfg.exposure = False
    plain = Trainer(TrainConfig("3dgs", "test", cfg, None, tc.__class__(**{**tc.__dict__, "run_name": "p"})),
                    plugins, argv=[], scene=tiny_scene)
    plain.recon.load_state(state)
    with torch.no_grad():
        assert torch.equal(trainer.recon.render_view(view).rgb, plain.recon.render_view(view).rgb)


def test_a_run_recorded_before_exposure_resumes_without_it(tiny_scene, tmp_path):
    import json

    plugins = load_plugins()
    cfg = plugins.methods.get("3dgs").config_factory()
    cfg.exposure = False
    tc = TrainerConfig(max_steps=4, output_dir=tmp_path, run_name="old", checkpoint_every=2, progress=False,
                       eval_train_views=0)
    old = Trainer(TrainConfig("3dgs", "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    old.train()
    info_path = old.run_dir / "run.json"
    info = json.loads(info_path.read_text())
    for key in [k for k in info["settings"]["method"] if k.startswith("exposure")]:
        del info["settings"]["method"][key]  # as recorded before the setting existed
    info_path.write_text(json.dumps(info))
    new_cfg = plugins.methods.get("3dgs").config_factory()  # exposure on by default
    tc2 = TrainerConfig(max_steps=6, output_dir=tmp_path, run_name="old", resume=old.run_dir, progress=False,
                        eval_train_views=0)
    resumed = Trainer(TrainConfig("3dgs", "test", new_cfg, None, tc2), plugins, argv=[], scene=tiny_scene)
    assert resumed.step == 4 and resumed.model.exposure is None
    resumed.train()
    assert resumed.step == 6
    # a setting the recorded run did have is still compared
    other = plugins.methods.get("3dgs").config_factory()
    other.sh_degree_interval += 1
    tc3 = TrainerConfig(max_steps=8, output_dir=tmp_path, run_name="old", resume=old.run_dir, progress=False,
                        eval_train_views=0)
    with pytest.raises(ConfigError, match="sh_degree_interval"):
        Trainer(TrainConfig("3dgs", "test", other, None, tc3), plugins, argv=[], scene=tiny_scene)
