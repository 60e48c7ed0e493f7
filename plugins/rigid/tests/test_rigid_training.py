"""Rigid node inside the trainer: absent actors are neither rendered nor stepped, rows of each
instance stay contiguous through densification, and a resumed run matches an uninterrupted
one (row-sparse Adam state included)."""
import copy

import numpy as np
import torch

from omnire.method import MethodConfig
from omnire.nodes.background import BackgroundConfig
from omnire.plugins import load_plugins
from omnire.strategy import DensifyConfig
from omnire.trainer import TrainConfig, Trainer, TrainerConfig
from omnire_rigid.node import RigidConfig

from scene_helpers import assert_same_state, make_tiny_scene


def scene_with_short_lived_actor(root):
    """The tiny scene's car plus a second car present only in frames 0-1."""
    scene = make_tiny_scene(root, frames=6, holdout=0)
    early = copy.deepcopy(scene.tracks[0])
    early.track_id = "early-car"
    early.poses[:, 1, 3] += 2.5
    early.present[2:] = False
    scene.tracks.append(early)
    return scene.validate()


def trainer(scene, tmp_path, name, steps=40, resume=None, reset_every=30):
    method = MethodConfig(
        nodes={"background": BackgroundConfig(voxel_size=0.5, num_far_points=200),
               "rigid": RigidConfig(random_points_per_instance=100)},
        densify=DensifyConfig(refine_start=10, refine_every=10, reset_every=reset_every, grad_threshold=1e-4),
        sh_degree_interval=15, rasterizer="torch", dynamic_pixel_weight=5.0,
    )
    tc = TrainerConfig(max_steps=steps, output_dir=tmp_path, run_name=name, checkpoint_every=20, log_every=5,
                       progress=False, resume=resume, eval_train_views=0)
    return Trainer(TrainConfig("streetgs-like", "test", method, None, tc), load_plugins(), argv=[], scene=scene)


def test_absent_actor_is_not_stepped_and_rows_stay_grouped(tmp_path):
    scene = scene_with_short_lived_actor(tmp_path / "scene")
    tr = trainer(scene, tmp_path, "absent", steps=40, reset_every=0)
    rigid = tr.model.nodes["rigid"]
    assert rigid.track_ids == ["car-1", "early-car"]
    all_views = tr.train_views
    tr.train_views = [v for v in all_views if v.frame < 2]  # both cars present: both get momentum
    for _ in range(15):
        tr.train_step()
    early = rigid.gaussian_buffers["instance"] == 1
    assert bool(early.any())
    snapshot = {k: p.detach()[early].reshape(int(early.sum()), -1).clone() for k, p in rigid.gaussian_params.items()}
    state = tr.optimizers.optimizers["rigid"].state
    moments = [state[p]["exp_avg"][early] for p in rigid.gaussian_params.values() if "exp_avg" in state[p]]
    assert any(bool((m != 0).any()) for m in moments)  # dense Adam would keep moving these rows
    present_before = rigid.gaussian_params["means"].detach()[~early].clone()
    tr.train_views = [v for v in all_views if v.frame >= 2]  # the early car is absent from now on
    for _ in range(25):  # densifies at steps 20, 30, 40
        tr.train_step()
    instance = rigid.gaussian_buffers["instance"]
    assert bool((instance[1:] >= instance[:-1]).all()), "densification left instance rows interleaved"
    early = instance == 1
    for k, p in rigid.gaussian_params.items():
        kept = p.detach()[early].reshape(int(early.sum()), -1)
        # SH bands that joined since the snapshot (omnire/shbands.py) are zeros: not stepped
        width = snapshot[k].shape[1]
        assert not kept[:, width:].any(), k
        # not stepped: each surviving early row equals a row of the snapshot (pruning may drop some)
        assert all(bool((snapshot[k] == row).all(1).any()) for row in kept[:, :width]), k
    means = rigid.gaussian_params["means"].detach()[~early]
    assert len(means) != len(present_before) or not torch.equal(means, present_before)  # the other car trained


def test_resume_with_row_sparse_state_matches_uninterrupted_run(tmp_path):
    scene = scene_with_short_lived_actor(tmp_path / "scene")
    full = trainer(scene, tmp_path, "full")
    full.train()
    resumed = trainer(scene, tmp_path, "resumed", resume=full.run_dir / "checkpoints" / "step-000020.pt")
    assert resumed.step == 20
    resumed.train()
    assert_same_state(full.model.state_dict(), resumed.model.state_dict())
    assert np.array_equal(full.model.nodes["rigid"].gaussian_buffers["instance"].numpy(),
                          resumed.model.nodes["rigid"].gaussian_buffers["instance"].numpy())
