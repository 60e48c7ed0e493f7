"""Renders of one moment through several cameras (a rig) share the actor nodes' states and
outputs (omnire.nodes.base.MomentCache): the same images as computed afresh, recomputed
after any change of a node's tensors, and never kept under autograd (training)."""
import numpy as np
import torch

from omnire.data.scene import ActorTrack
from omnire.plugins import load_plugins
from omnire.trainer import TrainConfig, Trainer, TrainerConfig


def omnire_trainer(scene, tmp_path):
    """The omnire method on ``scene`` with a pedestrian walking in front of the cameras."""
    F = scene.num_frames
    poses = np.tile(np.eye(4), (F, 1, 1))
    poses[:, 0, 3] = 5.0 + 0.1 * np.arange(F)
    poses[:, 1, 3] = -0.8
    poses[:, 2, 3] = -0.625
    scene.tracks.append(ActorTrack("ped-1", "Pedestrian", "human", poses, np.array([0.6, 0.6, 1.75]),
                                   np.ones(F, bool)))
    plugins = load_plugins()
    cfg = plugins.methods.get("omnire").config_factory()
    tc = TrainerConfig(max_steps=1, output_dir=tmp_path, run_name="omnire", progress=False, eval_train_views=0)
    return Trainer(TrainConfig("omnire", "test", cfg, None, tc), plugins, argv=[], scene=scene)


def fresh_render(recon, camera, t):
    """A render with every actor node's kept states and outputs dropped first."""
    for node in recon.actor_nodes().values():
        node.moment_outputs = type(node.moment_outputs)()
    return recon.render(camera, t)


def test_cameras_of_one_moment_share_node_outputs_and_render_the_same(tiny_scene, tmp_path):
    trainer = omnire_trainer(tiny_scene, tmp_path)
    recon = trainer.recon
    actors = recon.actor_nodes()
    assert {"rigid", "smpl"} <= set(actors) and all(len(n.state_at(recon.time(1)).ids) for n in actors.values())
    t = recon.time(1)
    cameras = [recon.camera(v) for v in trainer.train_views if v.frame == 1]
    assert len(cameras) >= 2
    with torch.no_grad():
        shared = [recon.render(c, t) for c in cameras]  # the second camera on reads kept outputs
        for camera, result in zip(cameras, shared):
            alone = fresh_render(recon, camera, t)
            assert torch.equal(result.rgb, alone.rgb) and torch.equal(result.depth, alone.depth)
        # kept: the same output object for a second camera that sees the same actors
        for node in actors.values():
            first = node.gaussians_at(t, cameras[0])
            assert node.gaussians_at(t, cameras[0]) is first
            assert node.gaussians_at(t, None) is node.gaussians_at(t, None)
        # another moment is another entry
        other = recon.time(2)
        assert not torch.equal(recon.render(cameras[0], other).rgb, shared[0].rgb)
        assert torch.equal(recon.render(cameras[0], t).rgb, shared[0].rgb)


def test_a_changed_node_tensor_drops_what_was_kept(tiny_scene, tmp_path):
    trainer = omnire_trainer(tiny_scene, tmp_path)
    recon = trainer.recon
    camera, t = recon.camera(trainer.train_views[0]), recon.time(trainer.train_views[0].frame)
    with torch.no_grad():
        before = recon.render(camera, t)
        for node in recon.actor_nodes().values():
            kept = node.gaussians_at(t, camera)
            node.gaussian_params["means"] += 0.05  # in place: the version counter moves
            moved = node.gaussians_at(t, camera)
            assert moved is not kept
            node.poses.delta_t += 0.1  # a pose refinement (a parameter of a submodule)
            assert node.gaussians_at(t, camera) is not moved
        after = recon.render(camera, t)
        assert not torch.equal(after.rgb, before.rgb)
        assert torch.equal(after.rgb, fresh_render(recon, camera, t).rgb)
        # a replaced tensor (densification, loading a checkpoint) drops them too
        node = recon.actor_nodes()["rigid"]
        kept = node.gaussians_at(t, camera)
        node.gaussian_params["opacities"] = torch.nn.Parameter(node.gaussian_params["opacities"] - 1.0)
        assert node.gaussians_at(t, camera) is not kept
    assert torch.equal(recon.render(camera, t).rgb, fresh_render(recon, camera, t).rgb)


def test_training_keeps_nothing(tiny_scene, tmp_path):
    trainer = omnire_trainer(tiny_scene, tmp_path)
    recon = trainer.recon
    t = recon.time(trainer.train_views[0].frame)
    for node in recon.actor_nodes().values():
        a, b = node.gaussians_at(t, None), node.gaussians_at(t, None)
        assert a is not b
        assert (a.gaussians if a.placement is None else a.local).means.requires_grad


def turned(camera, yaw: float):
    """``camera`` turned by ``yaw`` radians about the world's vertical axis through its centre."""
    import dataclasses
    import math

    c, s = math.cos(yaw), math.sin(yaw)
    Rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=camera.cam_to_world.dtype)
    pose = camera.cam_to_world.clone()
    pose[:3, :3] = Rz @ pose[:3, :3]
    return dataclasses.replace(camera, cam_to_world=pose, _world_to_cam=None)


def test_cameras_seeing_other_actors_share_every_present_actor(tiny_scene, tmp_path):
    """Once a second camera at a moment sees other actors than the first, the node draws
    every present actor once for all the cameras at that moment: still the same images."""
    import copy

    side = copy.deepcopy(tiny_scene.tracks[0])  # a second car farther on, to the left
    side.track_id = "car-2"
    side.poses[:, 0, 3] += 6.0
    side.poses[:, 1, 3] += 4.0
    tiny_scene.tracks.append(side)
    trainer = omnire_trainer(tiny_scene, tmp_path)
    recon = trainer.recon
    rigid = recon.actor_nodes()["rigid"]
    t = recon.time(1)
    base = recon.camera(trainer.train_views[0])
    cameras = [turned(base, yaw) for yaw in (-0.6, 0.0, 0.6, -0.3, 1.5)]
    with torch.no_grad():
        seen = [tuple(rigid.in_view(rigid.state_at(t), c).ids.tolist()) for c in cameras]
        assert len({s for s in seen if s}) >= 2, seen  # cameras that see different cars
        shared = [recon.render(c, t) for c in cameras]
        every = [rigid.gaussians_at(t, c) for c, s in zip(cameras, seen) if s]
        assert all(out is every[0] for out in every)
        assert len(every[0].placement.lengths) == 2  # both cars
        for camera, result in zip(cameras, shared):
            alone = fresh_render(recon, camera, t)
            assert torch.equal(result.rgb, alone.rgb) and torch.equal(result.depth, alone.depth)


def test_moment_cache_keeps_the_latest_keys_until_a_source_changes():
    from omnire.nodes.base import MomentCache

    a, b = torch.zeros(3), torch.ones(2)
    cache, calls = MomentCache(size=2), []

    def value(key):
        return lambda: calls.append(key) or key * 10

    assert cache.get((a, b), 1, value(1)) == 10 and cache.get((a, b), 2, value(2)) == 20
    assert cache.get((a, b), 1, value(1)) == 10 and calls == [1, 2]  # kept
    assert cache.get((a, b), 3, value(3)) == 30  # 2 was the least recent: dropped
    assert cache.holds((a, b), 1) and cache.holds((a, b), 3) and not cache.holds((a, b), 2)
    a += 1  # changed in place
    assert not cache.holds((a, b), 1)
    assert cache.get((a, b), 1, value(1)) == 10 and calls == [1, 2, 3, 1]
    assert not cache.holds((a, torch.ones(2)), 1)  # another tensor object
