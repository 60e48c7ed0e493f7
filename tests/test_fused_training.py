"""SceneModel renders with autograd through the cpu rasterizer's fused training path
(``rasterize_gaussians_train``) give the pixels, the loss gradients of every model parameter
and the densification statistics of :meth:`SceneModel.assemble` + :meth:`composite`
(``use_fused_training = False``). Kernel-level checks: plugins/cpu-rasterizer/tests/
test_fused_training.py."""
import pytest
import torch

from omnire.plugins import load_plugins
from omnire.strategy import AbsGradStrategy
from omnire.trainer import TrainConfig, Trainer, TrainerConfig

try:
    from omnire_rasterizer_cpu import available

    OK, REASON = available("cpu")
except ImportError as exc:  # the plugin is not installed
    OK, REASON = False, str(exc)
if not OK:
    pytest.skip(f"cpu rasterizer unavailable: {REASON}", allow_module_level=True)


def step_loss(trainer, view, result):
    """The training loss of ``result`` as :meth:`Trainer.train_step` forms it."""
    ctx = trainer.loss_context(view, result)
    terms = [weight * value for fn, weight in trainer.losses.values() if (value := fn(ctx)) is not None]
    reg_w = trainer.config.method.regularization_weights
    for node_name, output in result.outputs.items():
        for name, value in trainer.model.nodes[node_name].regularization(output).items():
            if reg_w.get(name, 0.0) != 0.0:
                terms.append(reg_w[name] * value)
    return sum(terms)


def render_and_backward(trainer, view, fused):
    model = trainer.model
    model.use_fused_training = fused
    assert model.fused_training() == fused
    for p in model.parameters():
        p.grad = None
    result = trainer.recon.render_view(view, step=trainer.step)
    loss = step_loss(trainer, view, result)
    loss.backward()
    # row-sparse parameters (omnire.rowsparse) get COO gradients: compare them dense
    grads = {n: (None if p.grad is None else p.grad.to_dense() if p.grad.is_sparse else p.grad.clone())
             for n, p in model.named_parameters()}
    return result, float(loss.detach()), grads


@pytest.mark.parametrize("method,step", [("omnire", 0), ("omnire", 3000), ("3dgs", 3000)])
def test_fused_training_path_matches_assemble_composite(method, step, tiny_scene, tmp_path):
    """Step 0 renders SH band 0 only (shN must get no gradient, not zeros: Adam would count
    the step), step 3000 all bands."""
    plugins = load_plugins()
    cfg = plugins.methods.get(method).config_factory()
    cfg.rasterizer = "cpu"
    tc = TrainerConfig(max_steps=1, output_dir=tmp_path, run_name=method, progress=False, eval_train_views=0)
    trainer = Trainer(TrainConfig(method, "test", cfg, None, tc), plugins, argv=[], scene=tiny_scene)
    trainer.recon.step = step
    with torch.no_grad():  # some large Gaussians straddling the image borders, some SH colour
        for node in trainer.model.gaussian_nodes().values():
            node.gaussian_params["scales"][::7] += 1.5
            node.gaussian_params["shN"].normal_(0.0, 0.1)
    nodes = trainer.model.gaussian_nodes()
    stats = {True: AbsGradStrategy(cfg.densify, trainer.model.scene_radius), False: AbsGradStrategy(
        cfg.densify, trainer.model.scene_radius)}
    culled = placed = False
    for view in trainer.train_views:
        fused, loss_f, grads_f = render_and_backward(trainer, view, True)
        ref, loss_r, grads_r = render_and_backward(trainer, view, False)
        cam = tiny_scene.cameras[view.camera]
        for fu, res in ((True, fused), (False, ref)):
            stats[fu].accumulate(nodes, res.slices, res.absgrad2d, res.radii, cam.width, cam.height)
        culled |= fused.num_gaussians < sum(len(o.gaussians) for o in fused.outputs.values())
        placed |= any(o.placement is not None for o in fused.outputs.values())  # actors drawn box-local
        torch.testing.assert_close(fused.rgb, ref.rgb, rtol=0, atol=2e-6)
        torch.testing.assert_close(fused.alpha, ref.alpha, rtol=0, atol=2e-6)
        torch.testing.assert_close(fused.depth, ref.depth, rtol=1e-5, atol=1e-4)
        assert abs(loss_f - loss_r) <= 1e-6 * max(1.0, abs(loss_r))
        assert grads_f.keys() == grads_r.keys()
        some = 0
        for name, gf in grads_f.items():
            gr = grads_r[name]
            if gr is None or gf is None:
                assert gr is None and gf is None, name
                continue
            some += int(gr.abs().sum() > 0)
            tol = 1e-4 * max(1e-3, float(gr.abs().max()))
            assert float((gf - gr).abs().max()) <= tol, (name, float((gf - gr).abs().max()), float(gr.abs().max()))
        assert some >= 6  # gradients reached several parameter tensors
        # rows of each node slice: drawn Gaussians and their AbsGrad agree node row by node row
        for name in fused.outputs:
            if name not in nodes:
                continue
            n = nodes[name].num_gaussians
            drawn = {}
            for res in (fused, ref):
                vis, ag = torch.zeros(n, dtype=torch.bool), torch.zeros(n, 2)
                for sl in res.slices:
                    if sl.node != name:
                        continue
                    rows = torch.arange(sl.start, sl.end) - sl.start if sl.rows is None else sl.rows
                    vis[rows] = res.radii[sl.start:sl.end] > 0
                    ag[rows] = res.absgrad2d[sl.start:sl.end].float()
                drawn[res is fused] = (vis, ag)
            assert torch.equal(drawn[True][0], drawn[False][0]), name
            torch.testing.assert_close(drawn[True][1], drawn[False][1], rtol=0,
                                       atol=1e-4 * max(1e-6, float(drawn[False][1].abs().max())))
    assert culled
    assert placed == (method == "omnire")
    for name in stats[False].state:
        a, b = stats[True].state[name], stats[False].state[name]
        assert torch.equal(a["count"], b["count"]), name
        torch.testing.assert_close(a["grad2d"], b["grad2d"], rtol=1e-4, atol=1e-6)
