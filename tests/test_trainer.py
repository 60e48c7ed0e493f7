"""Trainer end to end on a tiny scene with the reference rasterizer: loss goes down,
densification runs, checkpoints resume exactly, non-finite values are refused."""
import json

import pytest
import torch

from omnire.method import MethodConfig
from omnire.nodes.background import BackgroundConfig
from omnire.plugins import load_plugins
from omnire.strategy import DensifyConfig
from omnire.trainer import TrainConfig, Trainer, TrainerConfig, TrainingError

from scene_helpers import assert_same_state


def small_method(reset_every: int = 0, keep_after_growth: float = 1.0) -> MethodConfig:
    return MethodConfig(
        nodes={"background": BackgroundConfig(voxel_size=0.5, num_far_points=200)},
        densify=DensifyConfig(refine_start=10, refine_every=10, reset_every=reset_every, grad_threshold=2e-4,
                              keep_after_growth=keep_after_growth),
        sh_degree_interval=15,
        rasterizer="torch",
    )


def make_trainer(scene, tmp_path, steps=40, resume=None, name="run", checkpoint_every=20, reset_every=0,
                 keep_after_growth=1.0):
    plugins = load_plugins()
    tc = TrainerConfig(max_steps=steps, output_dir=tmp_path, run_name=name, checkpoint_every=checkpoint_every,
                       log_every=5, progress=False, resume=resume, eval_train_views=0)
    return Trainer(TrainConfig("3dgs", "test", small_method(reset_every, keep_after_growth), None, tc), plugins,
                   argv=[], scene=scene)


def test_training_reduces_loss_and_densifies(tiny_scene, tmp_path):
    trainer = make_trainer(tiny_scene, tmp_path, steps=60)
    n0 = trainer.model.num_gaussians()
    result = trainer.train()
    logs = [json.loads(line) for line in (trainer.run_dir / "metrics.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in logs if "loss" in r]
    assert sum(losses[-3:]) / 3 < 0.9 * sum(losses[:3]) / 3
    assert trainer.model.num_gaussians() != n0  # grown and/or pruned
    assert result["reconstruction"]["psnr"] > 14 and "novel_view" in result
    assert (trainer.run_dir / "checkpoints" / "step-000060.pt").is_file()
    for p in trainer.model.parameters():
        assert torch.isfinite(p).all()


def test_resume_matches_uninterrupted_run(tiny_scene, tmp_path):
    full = make_trainer(tiny_scene, tmp_path, steps=40, name="full", reset_every=30)
    full.train()
    ckpt = full.run_dir / "checkpoints" / "step-000020.pt"
    resumed = make_trainer(tiny_scene, tmp_path, steps=40, resume=ckpt, name="resumed", reset_every=30)
    assert resumed.step == 20
    resumed.train()
    assert_same_state(full.model.state_dict(), resumed.model.state_dict())


def test_non_finite_parameters_are_never_checkpointed(tiny_scene, tmp_path):
    trainer = make_trainer(tiny_scene, tmp_path, steps=5)
    with torch.no_grad():
        trainer.model.nodes["background"].gaussian_params["means"][3, 0] = float("nan")
    with pytest.raises(TrainingError, match="refusing to write a checkpoint"):
        trainer.save_checkpoint()
    assert not (trainer.run_dir / "checkpoints").exists()


def test_keep_gaussian_rows_cuts_parameters_moments_and_statistics_together(tiny_scene, tmp_path):
    trainer = make_trainer(tiny_scene, tmp_path, steps=20)
    for _ in range(3):  # Adam moments and densification statistics exist (refinement starts at 10)
        trainer.train_step()
    node = trainer.recon.gaussian_nodes()["background"]
    n = node.num_gaussians
    assert "background" in trainer.strategy.state
    keep = torch.rand(n, generator=torch.Generator().manual_seed(0)) < 0.4
    params = {k: p.detach().clone() for k, p in node.gaussian_params.items()}
    moments = {k: {s: v.clone() for s, v in trainer.optimizers.optimizers["background"].state[p].items()}
               for k, p in node.gaussian_params.items()}

    assert trainer.keep_gaussian_rows("background", keep) == (n, int(keep.sum()))
    for k, p in node.gaussian_params.items():  # the obvious selection, row by row
        rows = [i for i in range(n) if keep[i]]
        assert torch.equal(p.detach(), params[k][rows]), k
        state = trainer.optimizers.optimizers["background"].state[p]
        for s, old in moments[k].items():
            if s != "step":
                assert torch.equal(state[s], old[rows]), (k, s)
    assert "background" not in trainer.strategy.state
    trainer.train_step()  # training continues from the cut rows
    assert all(torch.isfinite(p).all() for p in node.gaussian_params.values())

    with pytest.raises(ValueError, match="expected torch.bool of shape"):
        trainer.keep_gaussian_rows("background", torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="expected one of the Gaussian nodes"):
        trainer.keep_gaussian_rows("sky", keep)


def test_pruning_when_growth_stops_keeps_the_fraction_asked_and_training_goes_on(tiny_scene, tmp_path):
    """``densify.keep_after_growth``: once, at the step growth stops (half of a 40-step
    schedule), each node keeps that fraction of its Gaussians (rounded up) and the run
    records it; the pruned run trains on, checkpoints and resumes."""
    trainer = make_trainer(tiny_scene, tmp_path, steps=40, checkpoint_every=10, keep_after_growth=0.4)
    while trainer.step < 20:
        trainer.train_step()
    stop = trainer.densify_stop
    assert stop is not None and stop["step"] == 20, stop
    before, after = stop["pruned"]["background"]
    assert after == -(-before * 4 // 10) == trainer.model.num_gaussians()
    result = trainer.train()
    assert trainer.step == 40 and result["reconstruction"]["psnr"] > 12
    assert trainer.model.num_gaussians() <= after  # no growth afterwards, transparent ones still go
    resumed = make_trainer(tiny_scene, tmp_path, steps=40, resume=trainer.run_dir, name="resumed",
                           keep_after_growth=0.4)
    assert resumed.densify_stop["pruned"] == stop["pruned"]
    assert resumed.model.num_gaussians() == trainer.model.num_gaussians()


def test_keep_after_growth_must_be_a_fraction():
    with pytest.raises(Exception, match="keep_after_growth"):
        DensifyConfig(keep_after_growth=0.0)
