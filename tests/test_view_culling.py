"""Culling Gaussians outside the view before colours and rasterization changes no pixel."""
import pytest
import torch

from omnire.plugins import load_plugins
from omnire.trainer import TrainConfig, Trainer, TrainerConfig


@pytest.mark.parametrize("method", ["3dgs", "streetgs"])
def test_culling_renders_the_same_images_with_fewer_gaussians(method, tiny_scene, tmp_path):
    plugins = load_plugins()
    cfg = plugins.methods.get(method).config_factory()
    tc = TrainerConfig(max_steps=1, output_dir=tmp_path, run_name=method, progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig(method, "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    with torch.no_grad():  # some large Gaussians straddling the image borders
        for node in trainer.model.gaussian_nodes().values():
            node.gaussian_params["scales"][::7] += 1.5
    fewer = False
    for view in trainer.train_views:
        with torch.no_grad():
            cfg.cull_to_view = True
            culled = trainer.recon.render_view(view)
            cfg.cull_to_view = False
            full = trainer.recon.render_view(view)
        torch.testing.assert_close(culled.rgb, full.rgb, rtol=0, atol=1e-6)
        torch.testing.assert_close(culled.depth, full.depth, rtol=0, atol=1e-5)
        fewer |= culled.num_gaussians < full.num_gaussians
        for sl in culled.slices:  # rendered rows map back to node rows
            assert sl.rows is None or len(sl.rows) == sl.end - sl.start
    assert fewer
