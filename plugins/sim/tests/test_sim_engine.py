"""The edit model on a small in-memory street (tests/sim_scene.py): an empty scenario renders
the recorded scene exactly; removing, moving, re-timing, stopping and inserting actors and
walking pedestrians change what they should and nothing else."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omnire.api import View, interpolate_poses
from omnire.camerapath import interpolated_path, log_seconds, path_at_times, recorded_path
from omnire_sim import ScenarioError, Simulation, parse_scenario
from omnire_sim.edits import Clock
from sim_scene import build, street_scene

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def no_grad():
    """Renders as the tools make them: without autograd (the inference path)."""
    with torch.no_grad():
        yield


def sim_of(recon, text: str, **kw) -> Simulation:
    return Simulation(recon, parse_scenario(text, "test.toml"), **kw)


def alpha_centroid(alpha: torch.Tensor) -> np.ndarray:
    """Alpha-weighted (u, v) centroid in pixels (pixel centres at +0.5)."""
    a = alpha[..., 0].double()
    v, u = torch.meshgrid(torch.arange(a.shape[0], dtype=torch.float64) + 0.5,
                          torch.arange(a.shape[1], dtype=torch.float64) + 0.5, indexing="ij")
    return np.array([float((a * u).sum() / a.sum()), float((a * v).sum() / a.sum())])


def test_empty_scenario_reproduces_recorded_renders(street):
    sim = sim_of(street, "")
    for view in street.scene.views(np.arange(street.scene.num_frames)):
        cam, t = street.camera(view), street.time(view.frame)
        a, b = street.render(cam, t), sim.render(cam, t)
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and torch.equal(a.alpha, b.alpha)


def test_identity_edits_reproduce_recorded_renders(street):
    """An actor edited with no change (speed 1, zero offset) is drawn through the edit path
    (its own gaussians_for call) and still gives the recorded pixels."""
    sim = sim_of(street, '[[actor]]\ntrack = "car-1"\nspeed = 1.0\n[[actor]]\ntrack = "ped-1"\noffset = [0, 0, 0]\n')
    for view in [View(0, 2), View(1, 5)]:
        cam, t = street.camera(view), street.time(view.frame)
        a, b = street.render(cam, t), sim.render(cam, t)
        torch.testing.assert_close(b.rgb, a.rgb, atol=1e-6, rtol=0)


@pytest.mark.parametrize("track", ["car-1", "ped-1", "bike-1"])
def test_removal_changes_only_the_actors_footprint(street, track):
    sim = sim_of(street, f'[[actor]]\ntrack = "{track}"\nremove = true\n')
    plain = sim_of(street, "")
    changed_any = False
    for view in [View(0, 1), View(1, 4), View(0, 7)]:
        cam, t = street.camera(view), street.time(view.frame)
        before, after = street.render(cam, t).rgb, sim.render(cam, t).rgb
        footprint = plain.render(cam, t, only={track}).alpha[..., 0] > 0
        changed = (before - after).abs().amax(-1) > 0
        assert not bool((changed & ~footprint).any()), f"{track}: pixels changed outside its footprint"
        changed_any |= bool(changed.any())
    assert changed_any


def project(cam, x: np.ndarray) -> np.ndarray:
    w2c = torch.linalg.inv(cam.cam_to_world).double().numpy()
    p = w2c[:3, :3] @ x + w2c[:3, 3]
    K = cam.K.double().numpy()
    return (K @ (p / p[2]))[:2]


def test_moved_rigid_actor_footprint_moves_as_projected(street):
    """car-2 moved 0.6 m sideways (parallel to the image plane of camera 0): the centroid of
    its footprint lands where the projection of its depth map, moved, says (< 1 px)."""
    view = View(0, 3)
    cam, t = street.camera(view), street.time(view.frame)
    plain = sim_of(street, "")
    offset = np.array([0.0, 0.6, 0.0])  # world y: camera 0 looks along +x
    moved = sim_of(street, '[[actor]]\ntrack = "car-2"\noffset_world = [0.0, 0.6, 0.0]\n')
    before = plain.render(cam, t, only={"car-2"})
    after = moved.render(cam, t, only={"car-2"})
    # expected: every footprint pixel back-projected with its depth, moved, re-projected
    a = before.alpha[..., 0].double().numpy()
    d = before.depth[..., 0].double().numpy()
    K = cam.K.double().numpy()
    c2w = cam.cam_to_world.double().numpy()
    v, u = np.nonzero(a > 1e-3)
    pix = np.stack([u + 0.5, v + 0.5, np.ones_like(u, dtype=float)], 1)
    rays = pix @ np.linalg.inv(K).T
    world = (rays * d[v, u][:, None]) @ c2w[:3, :3].T + c2w[:3, 3] + offset
    proj = np.stack([project(cam, x) for x in world])
    w = a[v, u]
    expected = (proj * w[:, None]).sum(0) / w.sum()
    got = alpha_centroid(after.alpha)
    shift = got - alpha_centroid(before.alpha)
    assert np.linalg.norm(shift) > 3.0  # it really moved
    assert np.linalg.norm(got - expected) < 1.0, (got, expected)


def test_offset_and_yaw_in_the_box_frame(street):
    sim = sim_of(street, '[[actor]]\ntrack = "car-1"\noffset = [1.0, 0.5, 0.0]\nyaw = 90\n')
    node = street.model.nodes["rigid"]
    t = street.time(2)
    rec = node.state_at(t)
    k = int(torch.nonzero(rec.ids == node.track_ids.index("car-1"))[0])
    state, _ = sim.actor("car-1").state(float(t.seconds - street.scene.frame_timestamps[0]), t)
    R0, t0 = rec.R[k].double(), rec.t[k].double()
    torch.testing.assert_close(state.t[0].double(), t0 + R0 @ torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64))
    yaw = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(state.R[0].double(), R0 @ yaw, atol=1e-6, rtol=0)


def test_stop_retime_and_clock(street):
    c = Clock(stop_at=0.4, brake=0.2)
    assert c(0.1) == pytest.approx(0.1) and c(0.4) == pytest.approx(0.3) and c(0.7) == pytest.approx(0.3)
    assert c.rate(0.3) == pytest.approx(0.5)
    resumed = Clock(speed=2.0, stop_at=0.2, resume_at=0.5)
    assert resumed(0.1) == pytest.approx(0.2) and resumed(0.5) == pytest.approx(0.4)
    assert resumed(0.6) == pytest.approx(0.6)
    sim = sim_of(street, '[[actor]]\ntrack = "car-1"\nstop_at = 0.3\n[[actor]]\ntrack = "ped-1"\nspeed = 2.0\n')
    car, ped = sim.actor("car-1"), sim.actor("ped-1")
    s3, s6 = car.state(0.3)[0], car.state(0.6)[0]
    torch.testing.assert_close(s3.t, s6.t)
    rigid = street.model.nodes["rigid"]
    rec = rigid.state_at(street.time(3))
    k = int(torch.nonzero(rec.ids == rigid.track_ids.index("car-1"))[0])
    torch.testing.assert_close(s6.t[0], rec.t[k])
    smpl = street.model.nodes["smpl"]
    torch.testing.assert_close(ped.state(0.2)[0].t[0], smpl.state_at(street.time(4)).t[0])
    assert ped.state(0.5) is None  # its time 1.0 s is past the log's end: absent


def test_insert_from_another_run_matches_its_render_there(street, tmp_path):
    """car-1 of run A drawn alone in run B (another scene, no actors) at pose P_B looks like
    car-1 drawn alone in A at pose P_A through a camera with the same relative pose."""
    recon_b = build(street_scene(tmp_path / "b", with_actors=False), seed=3)
    view = View(0, 4)
    cam_a, t_a = street.camera(view), street.time(view.frame)
    rigid = street.model.nodes["rigid"]
    st = rigid.state_at(t_a)
    k = int(torch.nonzero(st.ids == rigid.track_ids.index("car-1"))[0])
    P_a = torch.eye(4, dtype=torch.float64)
    P_a[:3, :3], P_a[:3, 3] = st.R[k].double(), st.t[k].double()
    yaw, xyz = 30.0, (4.0, -1.5, -0.7)
    source_time = t_a.seconds - street.scene.frame_timestamps[0]
    text = (f'[[insert]]\nid = "guest"\nrun = "run-a"\ntrack = "car-1"\nsource_time = {source_time}\n'
            f'trajectory = [{{t = 0.0, x = {xyz[0]}, y = {xyz[1]}, z = {xyz[2]}, yaw = {yaw}}}]\n')
    scenario = parse_scenario(text, "test.toml")
    run_a = scenario.resolve_path(scenario.inserts[0].run).resolve()
    sim_b = Simulation(recon_b, scenario, assets={run_a: street})
    P_b = torch.eye(4, dtype=torch.float64)
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    P_b[:3, :3] = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
    P_b[:3, 3] = torch.tensor(xyz, dtype=torch.float64)
    c2w_b = P_b @ torch.linalg.inv(P_a) @ cam_a.cam_to_world.double()
    cam_b = cam_a.with_pose(c2w_b.float())
    in_a = sim_of(street, "").render(cam_a, t_a, only={"car-1"})
    in_b = sim_b.render(cam_b, recon_b.time(2), only={"guest"})
    assert float(in_a.alpha.sum()) > 20
    torch.testing.assert_close(in_b.alpha, in_a.alpha, atol=2e-4, rtol=0)
    torch.testing.assert_close(in_b.rgb, in_a.rgb, atol=2e-4, rtol=0)
    full = sim_b.render(cam_b, recon_b.time(2))
    assert torch.isfinite(full.rgb).all()


def test_walking_pedestrian(street):
    text = ('[[actor]]\ntrack = "ped-1"\n'
            'trajectory = [{t = 0.0, x = 7.0, y = 2.0}, {t = 0.7, x = 7.0, y = -1.5}]\nmotion = "gait"\n')
    sim = sim_of(street, text)
    actor = sim.actor("ped-1")
    node = street.model.nodes["smpl"]
    bodies, times = [], np.linspace(0.0, 0.7, 8)
    wp_t = np.array([0.0, 0.7])
    wp = np.tile(np.eye(4), (2, 1, 1))
    wp[:, :3, 3] = [[7.0, 2.0, np.nan], [7.0, -1.5, np.nan]]
    for t in times:
        state, own = actor.state(float(t))
        assert state.body.shape == (1, 24, 3, 3)
        bodies.append(state.body[0, 1:])
        # the root follows the path: interpolated waypoints (z = the recorded height)
        expect = interpolate_poses(wp_t, np.nan_to_num(wp), t)[0]
        np.testing.assert_allclose(state.t[0, :2].double().numpy(), expect[:2, 3], atol=1e-5)
        # heading along the path (-y), body upright
        np.testing.assert_allclose(state.R[0, :2, 0].double().numpy(), [0.0, -1.0], atol=1e-5)
        out = node.gaussians_for(state, own)
        means = out.gaussians.means
        assert torch.isfinite(means).all() and torch.isfinite(out.gaussians.quats).all()
        local = (means - state.t[0]) @ state.R[0]  # box frame
        half = torch.tensor([0.6, 0.6, 1.7]) / 2 + 0.35  # box + reach of swinging limbs
        assert bool((local.abs() <= half).all()), local.abs().amax(0)
    joint_motion = torch.stack([(bodies[i] - bodies[0]).abs().amax() for i in range(1, len(bodies))])
    assert float(joint_motion.max()) > 0.3  # legs and arms swing
    cam = street.camera(View(0, 3))
    img = sim.render(cam, street.time(3))
    assert torch.isfinite(img.rgb).all()


def test_walker_stops_and_stands(street):
    text = ('[[actor]]\ntrack = "ped-1"\n'
            'trajectory = [{t = 0.0, x = 7.0, y = 2.0}, {t = 0.7, x = 7.0, y = -1.5}]\n'
            'motion = "gait"\nstop_at = 0.4\nbrake = 0.2\n')
    actor = sim_of(street, text).actor("ped-1")
    a, b = actor.state(0.5)[0], actor.state(0.7)[0]
    torch.testing.assert_close(a.t, b.t)
    torch.testing.assert_close(a.body, b.body)
    hips = a.body[0, 1:3]  # standing: no hip swing
    torch.testing.assert_close(hips, torch.eye(3).expand(2, 3, 3), atol=1e-6, rtol=0)


def test_body_pose_sequence_from_file(street, tmp_path):
    T = 10
    aa = np.zeros((T, 23, 3))
    aa[:, 0, 0] = np.linspace(0, 0.9, T)  # left hip swings forward
    np.savez(tmp_path / "wave.npz", body_pose=aa, fps=10.0)
    text = ('[[actor]]\ntrack = "ped-1"\nmotion = "wave.npz"\nmotion_loop = false\n')
    sim = Simulation(street, parse_scenario(text, "test.toml", tmp_path))
    actor = sim.actor("ped-1")
    for t, angle in [(0.0, 0.0), (0.45, 0.45), (0.7, 0.7)]:
        R = actor.state(t)[0].body[0, 1]
        assert float(torch.acos((torch.trace(R) - 1) / 2)) == pytest.approx(angle, abs=1e-4)


def test_deformable_actor_moves_but_takes_no_body_motion(street):
    sim = sim_of(street, '[[actor]]\ntrack = "bike-1"\noffset_world = [0.0, 0.5, 0.0]\n')
    cam, t = street.camera(View(0, 2)), street.time(2)
    a = sim_of(street, "").render(cam, t, only={"bike-1"}).alpha
    b = sim.render(cam, t, only={"bike-1"}).alpha
    assert float((a - b).abs().max()) > 0.1
    with pytest.raises(ScenarioError, match="bike-1|deformable") as err:
        sim_of(street, '[[actor]]\ntrack = "bike-1"\nmotion = "gait"\n')
    assert "line 3" in str(err.value)


@pytest.mark.parametrize("text, needle", [
    ('[[actor]]\ntrack = "nope"\nremove = true\n', "no track 'nope'"),
    ('[[actor]]\ntrack = "car-1"\nstop_at = 9.5\n', "outside the log"),
    ('[[actor]]\ntrack = "car-1"\ntrajectory = [{t = 0.2, x = 1, y = 2}, {t = 30.0, x = 3, y = 2}]\n',
     "outside the log"),
    ('[[insert]]\nid = "g"\nrun = "nowhere"\ntrack = "car-1"\ntrajectory = [[0, 1, 2, 0]]\n', "asset run"),
])
def test_resolution_errors_name_the_line(street, text, needle, tmp_path):
    from omnire.plugins import load_plugins

    with pytest.raises(ScenarioError, match=needle) as err:
        Simulation(street, parse_scenario(text, "bad.toml", tmp_path), load_plugins())
    assert "bad.toml line" in str(err.value)


def test_ego_interpolation_at_recorded_timestamps(street):
    scene = street.scene
    sec = log_seconds(scene)
    path = path_at_times(scene, sec)
    for c, cam in enumerate(scene.cameras):
        assert np.array_equal(path.cam_to_world[c], np.asarray(cam.cam_to_world, dtype=np.float64))
    assert np.array_equal(path.scene_frames, np.arange(scene.num_frames))
    rec = recorded_path(scene)
    assert np.array_equal(rec.cam_to_world, path.cam_to_world)
    fine = interpolated_path(scene, fps=30.0)
    assert len(fine) == 22 and fine.fps == 30.0
    np.testing.assert_allclose(fine.cam_to_world[:, ::3], path.cam_to_world, atol=1e-9)
    # renders along the path at recorded moments equal the recorded renders
    sim = sim_of(street, "")
    for i in (0, 5):
        got = sim.render(path.camera(1, i), path.time(scene, i)).rgb
        assert torch.equal(got, street.render(street.camera(View(1, i)), street.time(i)).rgb)


def test_lane_shift_and_decoupled_scene_time(street):
    scene = street.scene
    path = recorded_path(scene)
    shifted = path.lane_shifted(2.0, 0.2, 0.5)
    move = shifted.cam_to_world[:, :, :3, 3] - path.cam_to_world[:, :, :3, 3]
    left = path.rig_to_world[:, :3, 1]  # the rig's left (cameras look along +x: +y)
    np.testing.assert_allclose(move[:, :3], 0.0, atol=1e-12)  # before the window (t <= 0.2)
    np.testing.assert_allclose(move[0, 5:], np.tile(2.0 * left[5:] / np.linalg.norm(left[5:], axis=1, keepdims=True),
                                                   (1, 1)), atol=1e-9)
    mid = np.linalg.norm(move[0, 3])
    assert 0.0 < mid < 2.0
    np.testing.assert_allclose(shifted.cam_to_world[:, :, :3, :3], path.cam_to_world[:, :, :3, :3])
    frozen = path.with_scene_time(scene, 0.3)
    np.testing.assert_allclose(frozen.scene_frames, 3.0, atol=1e-9)
    assert np.array_equal(frozen.cam_to_world, path.cam_to_world)
    slow = path.with_scene_speed(scene, 0.5)
    np.testing.assert_allclose(slow.scene_frames, np.arange(8) * 0.5)


def test_camera_path_from_a_file(street, tmp_path):
    from omnire.api import ConfigError
    from omnire.camerapath import file_path, rig_poses

    scene = street.scene
    sec = log_seconds(scene)
    rig = rig_poses(scene).copy()
    np.savez(tmp_path / "rig.npz", seconds=sec, rig_to_world=rig)
    path = file_path(scene, tmp_path / "rig.npz")
    np.testing.assert_allclose(path.cam_to_world, recorded_path(scene).cam_to_world, atol=1e-9)
    rig[:, 2, 3] += 1.0  # one metre higher, scene frozen at 0.2 s
    (tmp_path / "up.json").write_text(__import__("json").dumps(
        {"seconds": sec.tolist(), "rig_to_world": rig.tolist(), "scene_seconds": [0.2] * len(sec)}))
    up = file_path(scene, tmp_path / "up.json", cameras=["cam1"])
    assert up.names == ("cam1",)
    np.testing.assert_allclose(up.cam_to_world[0, :, 2, 3] - path.cam_to_world[1, :, 2, 3], 1.0, atol=1e-9)
    np.testing.assert_allclose(up.scene_frames, 2.0, atol=1e-9)
    np.savez(tmp_path / "bad.npz", seconds=sec, rig_to_world=rig[:3])
    with pytest.raises(ConfigError, match="rig_to_world"):
        file_path(scene, tmp_path / "bad.npz")
