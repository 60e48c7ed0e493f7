"""Per-frame box poses of actor nodes (omnire/nodes/actors.py, ActorPoses): a stationary track
is held at one pose with one refinement shared by its frames; a moving one refines each frame."""
from __future__ import annotations

import numpy as np
import torch

from omnire.data.scene import ActorTrack
from omnire.nodes.actors import ActorPoses, held_pose

F = 8
TRAIN = np.array([0, 1, 2, 3, 5, 6, 7])  # frame 4 held out


def box(x: float, y: float, yaw: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:3, 3] = [x, y, 0.8]
    return pose


def tracks() -> list[ActorTrack]:
    rng = np.random.default_rng(0)
    # A parked car annotated with 10-20 cm of jitter per frame, absent in frame 0.
    parked = np.stack([box(10 + rng.normal(0, 0.15), 3 + rng.normal(0, 0.15), 0.3 + rng.normal(0, 0.02))
                       for _ in range(F)])
    present = np.ones(F, bool)
    present[0] = False
    driving = np.stack([box(2.0 * f, -3, 0.0) for f in range(F)])
    size = np.array([4.5, 1.9, 1.6])
    return [ActorTrack("parked", "Car", "vehicle", parked, size, present, stationary=True),
            ActorTrack("driving", "Car", "vehicle", driving, size, np.ones(F, bool))]


def test_held_pose_is_the_annotation_nearest_the_median_centre():
    parked = tracks()[0]
    centres = parked.poses[parked.present][:, :3, 3]
    # Brute force: the present frame minimising the distance to the per-axis median centre.
    dist = [np.linalg.norm(c - np.median(centres, axis=0)) for c in centres]
    np.testing.assert_array_equal(held_pose(parked), parked.poses[parked.present][int(np.argmin(dist))])


def test_a_stationary_track_keeps_one_pose_and_shares_its_refinement():
    ts = tracks()
    poses = ActorPoses(ts, TRAIN, refine=True, device="cpu")
    held = torch.as_tensor(held_pose(ts[0]), dtype=torch.float32)
    for f in range(1, F):
        _, R, t = poses.at_frame(f, torch.tensor([0]))
        torch.testing.assert_close(R[0], held[:3, :3])
        torch.testing.assert_close(t[0], held[:3, 3])
    # The moving track keeps its own per-frame annotations.
    for f in range(F):
        _, _, t = poses.at_frame(f, torch.tensor([1]))
        torch.testing.assert_close(t[0], torch.tensor([2.0 * f, -3, 0.8]))

    # A loss on frame 2 alone moves the parked car in every frame, the held-out one included,
    # by the same amount; the driving car only at frame 2 and where frame 2 is interpolated.
    target = torch.tensor([0.05, -0.02, 0.0])
    opt = torch.optim.SGD([poses.delta_t, poses.delta_rot], lr=1.0)
    _, _, t2 = poses.at_frame(2)
    loss = ((t2 - torch.stack([held[:3, 3], torch.tensor([4.0, -3, 0.8])]) - target) ** 2).sum() / 2
    loss.backward()
    assert int((poses.delta_t.grad[0].abs().sum(-1) > 0).sum()) == 1  # one shared slot
    opt.step()
    with torch.no_grad():
        for f in range(1, F):
            _, _, t = poses.at_frame(f, torch.tensor([0]))
            torch.testing.assert_close(t[0] - held[:3, 3], target)
        moved = [float((poses.at_frame(f, torch.tensor([1]))[2][0] - torch.tensor([2.0 * f, -3, 0.8])).norm())
                 for f in range(F)]
    assert moved[2] > 0.05 and all(m == 0.0 for f, m in enumerate(moved) if f != 2)


def test_a_run_from_before_shared_slots_loads_as_it_was_trained():
    ts = tracks()
    trained = ActorPoses(ts, TRAIN, refine=True, device="cpu")
    with torch.no_grad():
        trained.delta_t.copy_(torch.randn_like(trained.delta_t) * 0.05)
    state = trained.state_dict()
    del state["delta_slot"]
    # Older runs stored every frame's annotated pose and refined every frame on its own.
    recorded = np.stack([t.poses for t in ts])
    state["base_t"] = torch.as_tensor(recorded[..., :3, 3], dtype=torch.float32)
    loaded = ActorPoses(ts, TRAIN, refine=True, device="cpu")
    loaded.load_state_dict(state)
    assert torch.equal(loaded.delta_slot, torch.arange(F).expand(2, F))
    for f in (1, 3, 4):
        _, _, t = loaded.at_frame(f, torch.tensor([0]))
        p, n, w = loaded.interp_prev[f], loaded.interp_next[f], loaded.interp_w[f]
        expected = state["base_t"][0, f] + (1 - w) * state["delta_t"][0, p] + w * state["delta_t"][0, n]
        torch.testing.assert_close(t[0], expected)
