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


def test_actors_out_of_view_are_skipped_and_the_images_unchanged(tiny_scene, tmp_path):
    """Renders leave out the actors the camera cannot see (their whole ball out of its
    view): same images, also when the camera-pose refinement turns the cameras away from
    their recorded poses (nodes cull against the refined camera). Training steps place every
    present actor, so a view that sees none still steps their Gaussians."""
    import copy

    import numpy as np

    away = copy.deepcopy(tiny_scene.tracks[0])  # a second car driving sideways out of view
    away.track_id = "car-2"
    away.poses[:, 1, 3] = 2.0 + 5.0 * np.arange(tiny_scene.num_frames)
    tiny_scene.tracks.append(away)
    plugins = load_plugins()
    cfg = plugins.methods.get("streetgs").config_factory()
    tc = TrainerConfig(max_steps=1, output_dir=tmp_path, run_name="streetgs", progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig("streetgs", "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    model = trainer.model
    assert model.gaussian_nodes()["rigid"].poses.num_instances == 2
    skipped = {}
    for yaw in (0.0, 0.35, -0.35):  # corrections far larger than any learned one
        with torch.no_grad():
            model.camera_poses.delta.zero_()
            model.camera_poses.delta[:, 1] = yaw
        for view in trainer.train_views:
            res = {}
            for cull in (True, False):
                cfg.cull_to_view = cull
                with torch.no_grad():
                    res[cull] = trainer.recon.render_view(view)
                res[cull, "grad"] = trainer.recon.render_view(view)  # autograd: the fused training path
                res[cull, "grad"].rgb.sum().backward()
            for a, b in ((res[True], res[False]), (res[True, "grad"], res[False, "grad"])):
                torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=1e-6)
                torch.testing.assert_close(a.depth, b.depth, rtol=0, atol=1e-5)
            rigid = {c: next(s for s in res[c].slices if s.node == "rigid") for c in (True, False)}
            skipped[yaw, view.frame, view.camera] = len(rigid[False].rows) - len(rigid[True].rows)
    cfg.cull_to_view = True
    assert max(skipped.values()) > 0  # the car out of view was left out
    # where it is left out follows the refined camera: turned one way it loses the car
    # sooner, turned the other way later than the recorded camera does
    assert skipped[0.35, 1, 0] > 0 == skipped[0.0, 1, 0] and skipped[-0.35, 2, 0] == 0 < skipped[0.0, 2, 0]
    # a view where the refined camera looks away from every actor: a render skips them all,
    # a training step places them all (their Gaussians keep their Adam steps) and trains
    with torch.no_grad():
        model.camera_poses.delta[:, 1] = 3.0
    view = trainer.train_views[0]
    rigid = model.gaussian_nodes()["rigid"]
    t = trainer.recon.time(view.frame)
    away = model.camera_poses.refined_camera(trainer.recon.camera(view), t)
    with torch.no_grad():
        out = rigid.gaussians_at(t, away)
    assert out is not None and len(out.gaussians) == 0
    out = rigid.gaussians_at(t, away)
    assert len(out.rows) == len(rigid.gaussians_at(t, None).rows) > 0
    trainer.train_step(view)
