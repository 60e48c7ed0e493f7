"""The scene runtime: what a Reconstruction carries, the one step counter, and ``drawn`` as
the one answer to "what is drawn at this moment" (render draws exactly it)."""
from __future__ import annotations

import dataclasses

import pytest
import torch
from scene_helpers import TINY_RUN_KEY, make_tiny_run

from omnire.nodes.actors import ActorNode
from omnire.plugins import load_plugins
from omnire.runtime import Reconstruction


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    run = make_tiny_run(tmp_path_factory.getbasetemp() / TINY_RUN_KEY)
    return Reconstruction.from_run(run, load_plugins())


def test_a_loaded_run_declares_where_it_came_from(recon):
    assert recon.run_info.method == "omnire" and recon.config.method_name == "omnire"
    assert recon.checkpoint.is_file() and recon.checkpoint.parent.parent == recon.run_dir.path
    copy = recon.snapshot()
    assert (copy.run_info, copy.run_dir, copy.step) == (recon.run_info, recon.run_dir, recon.step)
    assert copy.model is not recon.model and not any(p.requires_grad for p in copy.model.parameters())


def test_drawn_without_edits_is_every_gaussian_node_as_recorded(recon):
    t = recon.time(1)
    drawn = list(recon.drawn(t))
    assert [d.label for d in drawn] == list(recon.model.gaussian_nodes())
    for d in drawn:
        assert d.owner is recon and d.moment == t and not d.inserted
        if d.is_actor:
            ref = d.node.state_at(t)
            assert d.recorded and torch.equal(d.state.ids, ref.ids) and torch.equal(d.state.t, ref.t)
            assert d.keys == tuple(d.node.track_ids[i] for i in ref.ids.tolist())
        else:
            assert d.state is None and d.keys == ()
    assert [d.label for d in recon.drawn(t, hidden={"background"})] == [d.label for d in drawn[1:]]


@pytest.mark.parametrize("grad", [False, True])
def test_render_is_the_scene_models_own_composition(recon, grad):
    """recon.render (drawn -> node_outputs -> render_outputs) against the model's gather +
    composite, the plain concatenation of every node's output."""
    view = recon.scene.views(recon.scene.train_frames)[0]
    camera, t = recon.camera(view), recon.time(view.frame + 0.5)
    with torch.set_grad_enabled(grad):
        got = recon.render(camera, t)
        g, slices, outputs = recon.model.gather(camera, t)
        ref = recon.model.composite(g, slices, outputs, camera, t, recon.sh_degree())
    assert torch.equal(got.rgb, ref.rgb) and torch.equal(got.depth, ref.depth)


def test_render_cameras_side_by_side_equals_one_at_a_time(recon):
    """A rig's cameras rendered side by side (render_cameras: workers, one thread each) give
    the very images of rendering them one at a time, and the thread count is restored."""
    views = recon.scene.views(recon.scene.train_frames)
    frame = views[0].frame
    cameras = [recon.camera(v) for v in views if v.frame == frame] * 2  # more cameras than workers
    t = recon.time(frame + 0.5)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with torch.no_grad():
            alone = [recon.render(c, t) for c in cameras]
            together = recon.render_cameras(cameras, t)
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    assert len(together) == len(cameras)
    for a, b in zip(alone, together):
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and torch.equal(a.alpha, b.alpha)
        assert not b.rgb.requires_grad  # grad mode is per thread: the workers turned it off too


@dataclasses.dataclass
class Moved:
    """An edited actor: the recorded one shifted by ``offset`` metres (world frame)."""

    key: str
    node_name: str
    node: ActorNode
    owner: Reconstruction
    instance: int
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    removed: bool = False

    def state(self, seconds, time):
        st = self.node.state_at(time)
        hit = (st.ids == self.instance).nonzero().flatten()
        if len(hit) == 0:
            return None
        one = st.select(hit)
        return dataclasses.replace(one, t=one.t + torch.tensor(self.offset)), time


class Edits:
    """A minimal ActorEdits: one actor moved, one removed, one inserted (a copy of the moved one)."""

    def __init__(self, moved: Moved, removed: Moved, inserted: Moved) -> None:
        self.moved, self.removed, self.added = moved, removed, inserted

    def edited(self, node_name):
        return {a.instance: a for a in (self.moved, self.removed) if a.node_name == node_name}

    def inserted(self):
        return [self.added]


def test_edits_take_actors_out_of_the_recording_and_draw_them_alone(recon):
    t = recon.time(1)
    name, node = next((n, m) for n, m in recon.actor_nodes().items() if len(m.state_at(t).ids) >= 2)
    first, second = node.state_at(t).ids.tolist()[:2]
    keys = [node.track_ids[first], node.track_ids[second]]
    assert recon.find_actor(keys[0]) == (name, node, first)
    edits = Edits(Moved(keys[0], name, node, recon, first, (0.0, 0.0, 1.0)),
                  Moved(keys[1], name, node, recon, second, removed=True),
                  Moved("copy", name, node, recon, first, (2.0, 0.0, 0.0)))
    drawn = {d.label: d for d in recon.drawn(t, edits)}
    rest = drawn[name]
    assert not rest.recorded and not set(keys) & set(rest.keys)
    assert set(rest.keys) == {node.track_ids[i] for i in node.state_at(t).ids.tolist()} - set(keys)
    assert f"{name}:{keys[1]}" not in drawn  # removed
    moved = drawn[f"{name}:{keys[0]}"]
    assert moved.keys == (keys[0],) and torch.allclose(moved.state.t - node.state_at(t).t[0], torch.tensor([0, 0, 1.0]))
    assert drawn["insert:copy"].inserted and list(drawn)[-1] == "insert:copy"
    only = [d.label for d in recon.drawn(t, edits, only={"copy", keys[0]})]
    assert only == [f"{name}:{keys[0]}", "insert:copy"]
    with torch.no_grad():
        assert recon.render(recon.camera(recon.scene.views([1])[0]), t, edits=edits, only=set()).alpha.max() == 0


def test_the_trainer_advances_the_reconstructions_step(tiny_scene, tmp_path):
    from test_trainer import make_trainer

    from omnire.trainer import STEP_STAGES

    trainer = make_trainer(tiny_scene, tmp_path, steps=5)
    recon = trainer.recon
    assert recon.run_info is None and recon.config is None and recon.run_dir is None and recon.checkpoint is None
    seen = []
    trainer.train_step(on_stage=seen.append)
    assert tuple(seen) == STEP_STAGES and trainer.step == recon.step == 1
    trainer.save_checkpoint()
    assert torch.load(trainer.run.checkpoint_path(1), weights_only=False)["step"] == 1
