"""SH bands stored up to the training degree (omnire/shbands.py): training takes exactly the
steps it takes with every band stored, through degrees 0 -> 3, densification and a resume;
bands that hold anything are never dropped unless asked."""
import pytest
import torch

from omnire.method import MethodConfig
from omnire.nodes.background import BackgroundConfig
from omnire.plugins import load_plugins
from omnire.errors import ConfigError
from omnire.rasterization import select_rasterizer
from omnire.shbands import fit_sh_bands, sh_columns
from omnire.strategy import DensifyConfig
from omnire.trainer import TrainConfig, Trainer, TrainerConfig

from scene_helpers import assert_same_state


def _trainer(scene, tmp_path, rasterizer, name, steps=44, resume=None):
    method = MethodConfig(
        nodes={"background": BackgroundConfig(voxel_size=0.5, num_far_points=200)},
        densify=DensifyConfig(refine_start=8, refine_every=8, reset_every=0, grad_threshold=2e-4),
        sh_degree_interval=10, rasterizer=rasterizer)
    tc = TrainerConfig(max_steps=steps, output_dir=tmp_path, run_name=name, checkpoint_every=22, log_every=11,
                       progress=False, resume=resume, eval_train_views=0)
    return Trainer(TrainConfig("3dgs", "test", method, None, tc), load_plugins(), argv=[], scene=scene)


def _rasterizers():
    names = ["torch"]
    try:
        select_rasterizer(load_plugins(), "cpu", "cpu")
        names.append("cpu")  # the fused training path
    except ConfigError:
        pass
    return names


def _assert_equal_states(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if torch.is_tensor(a[k]):
            assert a[k].shape == b[k].shape and torch.equal(a[k], b[k]), k


@pytest.mark.parametrize("rasterizer", _rasterizers())
def test_training_with_fitted_bands_takes_the_steps_of_all_bands_stored(tiny_scene, tmp_path, monkeypatch, rasterizer):
    fitted = _trainer(tiny_scene, tmp_path, rasterizer, "fitted")
    seen = []
    original = Trainer.fit_sh_bands

    def record(self, discard_unused=False):
        changed = original(self, discard_unused)
        seen.append((self.step, sh_columns(self.model.gaussian_nodes())["background"]))
        return changed

    monkeypatch.setattr(Trainer, "fit_sh_bands", record)
    fitted.train()
    assert (0, 0) in seen and (10, 3) in seen and (20, 8) in seen and (30, 15) in seen
    monkeypatch.setattr(Trainer, "fit_sh_bands", lambda self, discard_unused=False: {})
    full = _trainer(tiny_scene, tmp_path, rasterizer, "full")
    full.train()
    assert sh_columns(full.model.gaussian_nodes())["background"] == 15
    _assert_equal_states(full.model.state_dict(), fitted.model.state_dict())
    opt_full = full.optimizers.optimizers["background"].state_dict()["state"]
    opt_fit = fitted.optimizers.optimizers["background"].state_dict()["state"]
    for k in opt_full:
        for name in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt_full[k][name], opt_fit[k][name]), (k, name)


def test_resume_across_a_degree_change(tiny_scene, tmp_path):
    full = _trainer(tiny_scene, tmp_path, "torch", "full", steps=30)
    full.train()
    ckpt = full.run_dir / "checkpoints" / "step-000022.pt"  # degree 2: 8 columns stored
    resumed = _trainer(tiny_scene, tmp_path, "torch", "resumed", steps=30, resume=ckpt)
    assert sh_columns(resumed.model.gaussian_nodes())["background"] == 8
    resumed.train()
    assert_same_state(full.model.state_dict(), resumed.model.state_dict())


def test_bands_holding_anything_are_kept_unless_discarded(tiny_scene, tmp_path):
    trainer = _trainer(tiny_scene, tmp_path, "torch", "t", steps=1)
    nodes = trainer.model.gaussian_nodes()
    shN = nodes["background"].gaussian_params["shN"]
    assert shN.shape[1] == 15 and not shN.any()
    with torch.no_grad():
        shN[0, 9, 1] = 0.25  # band 3
    assert fit_sh_bands(nodes, trainer.optimizers, 2) == {}
    assert fit_sh_bands(nodes, trainer.optimizers, 2, discard_unused=True) == {"background": (15, 8)}
    assert fit_sh_bands(nodes, trainer.optimizers, 1) == {"background": (8, 3)}  # zeros: dropped
    assert fit_sh_bands(nodes, trainer.optimizers, 3) == {"background": (3, 15)}
    grown = nodes["background"].gaussian_params["shN"]
    assert grown.shape == shN.shape and not grown.any()
    assert trainer.optimizers.groups["background"][[s.key for s in trainer.optimizers.groups["background"]].index("shN")
                                                   ].params[0] is grown
