"""omnire view: the scene drawn by a real browser (headless Chromium) agrees with the server's
rasterizer; the time slider moves and re-skins actors; hide/move edits are the simulation's
(omnire_sim) and --scenario shows a simulated scene; picking; the training observer; clear
errors for a run without checkpoint, a busy port and a bad scenario."""
from __future__ import annotations

import contextlib
import math
import socket
import time
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from omnire.api import Reconstruction, UserError, rotmat_to_quat, sensor_path
from omnire_sim import ActorEdit as SimActorEdit
from omnire_sim import Placement, Scenario, Simulation, load_scenario
from omnire_viewer.app import PortInUseError, Viewer
from omnire_viewer.cli import main as view_main
from omnire_viewer.edits import ActorEdit
from omnire_viewer.headless import HeadlessChromium, find_chromium
from omnire_viewer.scene import ViewerScene

FRAME = 2
# Returns the 3D view's size on the page (CSS pixels), which is what a screenshot shows: its
# drawing buffer shrinks when viser's adaptive resolution finds frames slow (a loaded machine:
# 315x210 seen for a 360x240 window) and is scaled up to the same place.
SHOW_ONLY_CANVAS = """(() => {
  const canvases = [...document.querySelectorAll('canvas')].sort((a, b) => b.width * b.height - a.width * a.height);
  document.body.style.visibility = 'hidden';   // the control panel, notifications, logo ...
  canvases[0].style.visibility = 'visible';    // ... all but the 3D view
  const rect = canvases[0].getBoundingClientRect();
  return [Math.round(rect.width), Math.round(rect.height)];
})()"""


@pytest.fixture(scope="module")
def recon(tiny_run, plugins):
    return Reconstruction.from_run(tiny_run, plugins)


@contextlib.contextmanager
def opened(recon):
    """A viewer of ``recon`` on a free port at :data:`FRAME`, closed afterwards."""
    v = Viewer(ViewerScene(recon), "127.0.0.1", 0, frame=FRAME, verbose=False)
    try:
        yield v
    finally:
        v.close()


@pytest.fixture()
def viewer(recon):
    with opened(recon) as v:
        yield v


def blocks(image: np.ndarray, size: int) -> np.ndarray:
    """(H, W, 3) -> (H // size, W // size, 3) block means."""
    H, W = image.shape[0] // size * size, image.shape[1] // size * size
    return image[:H, :W].reshape(H // size, size, W // size, size, 3).mean(axis=(1, 3))


def histogram(image: np.ndarray, bins: int = 16) -> np.ndarray:
    """(3, bins) per-channel histograms of an image in [0, 1], each summing to 1."""
    return np.stack([np.histogram(image[..., c], bins=bins, range=(0, 1))[0] / image[..., c].size for c in range(3)])


def page_client(browser: HeadlessChromium, viewer: Viewer):
    """Open ``viewer``'s page in ``browser``; the viser client of that page once it connects."""
    browser.navigate(viewer.url)
    deadline = time.monotonic() + 60
    while not viewer.server.get_clients():
        assert time.monotonic() < deadline, f"the page never connected: {browser.log_tail()}"
        time.sleep(0.1)
    return next(iter(viewer.server.get_clients().values()))


def settled_screenshot(browser: HeadlessChromium, drawn: bool, timeout: float = 60.0) -> np.ndarray:
    """A screenshot once the browser's image has stopped changing for three shots in a row
    (the page loads, splats fade in and are sorted asynchronously after every change); with
    ``drawn``, also waiting while the view is still a flat page. Returns the last shot at
    the timeout, for the assertions to report."""
    shots, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        time.sleep(0.6)
        shots = (shots + [browser.screenshot().astype(np.float64) / 255.0])[-3:]
        stable = len(shots) == 3 and all(np.abs(s - shots[-1]).mean() < 0.5 / 255 for s in shots[:-1])
        if stable and (not drawn or shots[-1].std() > 0.02):
            break
    return shots[-1]


@pytest.mark.skipif(find_chromium() is None, reason="headless browser test: no chromium on PATH "
                    "(Debian: apt-get install chromium; .ci/run installs it)")
def test_browser_draws_the_scene_like_the_server(viewer, recon, tmp_path):
    import imageio.v3 as iio

    viewer.gui_boxes.value = False    # overlays the server does not draw
    viewer.gui_cameras.value = False
    W, H = 360, 240
    with HeadlessChromium(width=W, height=H) as browser:
        client = page_client(browser, viewer)
        cam = recon.scene.cameras[0]
        viewer.look_through(client, cam.cam_to_world[FRAME], cam.intrinsics, cam.height)
        assert viewer.wait_idle()
        deadline = time.monotonic() + 30
        while np.abs(np.asarray(client.camera.position) - cam.cam_to_world[FRAME, :3, 3]).max() > 1e-4:
            assert time.monotonic() < deadline, "the browser camera did not reach the dataset camera"
            time.sleep(0.1)
        assert browser.evaluate(SHOW_ONLY_CANVAS) == [W, H]
        shot = settled_screenshot(browser, drawn=True)
        camera = viewer.client_camera(client)
        assert (camera.width, camera.height) == (W, H)
        server = viewer.scene.render(camera, FRAME, viewer.hidden_nodes())
        iio.imwrite(tmp_path / "browser.png", (shot * 255).astype(np.uint8))
        iio.imwrite(tmp_path / "server.png", (server * 255).astype(np.uint8))

        # The scene is drawn: structure, not a flat page (the empty UI is white, see below).
        assert shot.std() > 0.05
        # Colours agree region by region. The browser quantises colours and opacities to
        # 8 bits and covariances to float16, cuts splats at 2.8 sigma and below alpha 0.01
        # (the rasterizer: alpha 1/255, capped at 0.99), sorts splats by centre depth
        # globally (the rasterizer per tile) and approximates the sky by a far shell of
        # splats. These move edges and thin overlaps, not the colour of a 12x12-pixel
        # region: block means agree to a few percent on average, while a view turned by
        # 20 degrees differs by several times that (checked below), so 0.05 separates
        # "same picture" from "another picture" with margin on both sides.
        diff = np.abs(blocks(shot, 12) - blocks(server, 12))
        hist = np.abs(histogram(shot) - histogram(server)).sum(axis=1).max()
        print(f"block mean abs diff {diff.mean():.4f} (95th pct {np.percentile(diff, 95):.4f}), "
              f"histogram L1 {hist:.3f}")
        assert diff.mean() < 0.05 and np.percentile(diff, 95) < 0.2
        assert hist < 0.5  # most of each histogram's mass in the same 1/16-wide bins

        turned = cam.cam_to_world[FRAME].copy()
        c, s = math.cos(math.radians(20)), math.sin(math.radians(20))
        turned[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ turned[:3, :3]
        other = viewer.scene.render(camera.with_pose(torch.as_tensor(turned, dtype=torch.float32)), FRAME)
        wrong = np.abs(blocks(shot, 12) - blocks(other, 12)).mean()
        assert wrong > 2 * diff.mean(), f"a turned view differs by only {wrong:.4f}: the test cannot tell views apart"

        # The panel's server render is that same image.
        np.testing.assert_allclose(viewer.render_for_client(client), server, atol=1e-6)
        assert viewer.gui_render_image.visible

        # Click an actor in the browser: the click's ray selects it and the panel names it.
        K, w2c = camera.K.double().numpy(), camera.world_to_cam.double().numpy()
        centre = camera.center.double().numpy()
        candidates = []
        for tid, (_R, c, _size) in viewer.scene.actor_boxes(FRAME).items():
            p = w2c[:3, :3] @ c + w2c[:3, 3]
            u, v = (K @ p)[:2] / p[2]
            if p[2] > 1 and 10 < u < W - 10 and 10 < v < H - 10:
                candidates.append((p[2], tid, u, v))
        assert candidates, "an actor is in view"
        _, target, u, v = min(candidates)
        ray = camera.cam_to_world[:3, :3].double().numpy() @ np.linalg.solve(K, [u, v, 1.0])
        expected = viewer.scene.pick(centre, ray, FRAME)
        assert expected is not None
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            browser.call("Input.dispatchMouseEvent", type=kind, x=float(u), y=float(v), button="left", clickCount=1)
        deadline = time.monotonic() + 20
        while viewer.selected != expected:
            assert time.monotonic() < deadline, f"clicking {target} in the browser selected {viewer.selected}"
            time.sleep(0.1)
        info = viewer.scene.actors[expected]
        assert expected in viewer.gui_actor_info.content and info.class_name in viewer.gui_actor_info.content

        # Not the empty UI: with every node switched off the page is blank and uniform.
        for box in viewer.gui_nodes.values():
            box.value = False
        assert viewer.wait_idle()
        empty = settled_screenshot(browser, drawn=False)
        assert empty.std() < 0.02 and np.abs(empty - shot).mean() > 0.1


def test_time_slider_moves_rigid_actors_and_reskins_pedestrians(viewer, recon):
    viewer.wait_idle()
    before = {name: (version, pos.copy()) for name, (h, version) in viewer._handles.items()
              for pos in [np.asarray(h.position)]}
    viewer.gui_frame.value = 6.0
    viewer._dirty.set()
    assert viewer.wait_idle()
    boxes = viewer.scene.actor_boxes(6.0)
    moved = reskinned = 0
    for name, (handle, version) in viewer._handles.items():
        if not name.startswith("/actors/"):
            continue
        node, tid = name.split("/")[2:4]
        np.testing.assert_allclose(handle.position, boxes[tid][1], atol=1e-5)  # placed by its box at frame 6
        if name in before:
            old_version, old_pos = before[name]
            if node == "rigid":
                assert version == old_version, "a rigid actor is moved, not re-sent"
                moved += np.abs(old_pos - boxes[tid][1]).max() > 1e-3
            elif node == "smpl":
                reskinned += version != old_version
    assert moved > 0 and reskinned > 0
    # objects follow presence: every object drawn is present at frame 6 and vice versa
    drawn = {n.split("/")[3] for n in viewer._handles if n.startswith("/actors/")}
    assert drawn == set(boxes)


def test_time_line_counts_from_the_first_frame(viewer, recon):
    """The caption under the slider gives seconds since the first frame (the clock of omnire
    sim and of scenario files; the log's Unix time means nothing to a reader) and the frame."""
    stamps = recon.scene.frame_timestamps
    for frame in (0.0, 2.5, 6.0):
        viewer.gui_frame.value = frame
        viewer._dirty.set()
        assert viewer.wait_idle()
        seconds = float(recon.time(frame).seconds - stamps[0])
        assert viewer.gui_seconds.content == (f"frame {frame:.1f} of 0-{recon.scene.num_frames - 1}  \n"
                                              f"t = {seconds:.3f} s since the first frame")


def sim_rgb(recon, camera, frame, scenario, plugins=None) -> np.ndarray:
    """(H, W, 3) what ``omnire sim`` renders of ``scenario`` through ``camera`` at ``frame``."""
    return Simulation(recon, scenario, plugins).render(camera, recon.time(frame)).rgb.clamp(0, 1).numpy()


@torch.no_grad()
def assert_placed_like_the_sim(viewer, sim, frame):
    """Every actor object in the browser sits where the simulation puts that actor's box at
    ``frame`` (the recorded pose for unedited actors), and no other actor is drawn."""
    recon = viewer.scene.recon
    time_ = recon.time(frame)
    t = time_.seconds - float(recon.scene.frame_timestamps[0])
    expected = {}
    edited = {(a.node_name, a.instance): a for a in sim.actors if not a.inserted}
    for name, node in recon.nodes.items():
        if name not in ("rigid", "smpl"):
            continue
        st = node.state_at(time_)
        for k, i in enumerate(st.ids.tolist()):
            if (name, i) not in edited:
                expected[f"/actors/{name}/{node.track_ids[i]}"] = (st.R[k], st.t[k])
    for actor in sim.actors:
        got = None if actor.removed else actor.state(t, time_)
        if got is not None:
            key = f"/actors/insert/{actor.key}" if actor.inserted else f"/actors/{actor.node_name}/{actor.key}"
            expected[key] = (got[0].R[0], got[0].t[0])
    drawn = {n: h for n, (h, _v) in viewer._handles.items() if n.startswith("/actors/")}
    assert set(drawn) == set(expected)
    for key, (R, tr) in expected.items():
        np.testing.assert_allclose(drawn[key].position, tr.double().numpy(), atol=1e-5, err_msg=key)
        q = np.asarray(drawn[key].wxyz)
        q_sim = rotmat_to_quat(R.double()).numpy()
        assert min(np.abs(q - q_sim).max(), np.abs(q + q_sim).max()) < 1e-5, key


def test_hide_move_and_pick(viewer, recon):
    """Hide and move go through the simulation: the server render and the browser objects
    are those of omnire_sim's Simulation with remove / Placement for the same tracks."""
    sc = viewer.scene
    cam = recon.scene.cameras[0]
    camera = recon.camera(recon.scene.views([FRAME])[0])
    boxes = sc.actor_boxes(FRAME)
    # the car nearest the camera, and a ray from the camera through its box centre
    car = min((t for t in boxes if sc.actors[t].node == "rigid"),
              key=lambda t: np.linalg.norm(boxes[t][1] - cam.cam_to_world[FRAME, :3, 3]))
    ped = min((t for t in boxes if sc.actors[t].node == "smpl"),
              key=lambda t: np.linalg.norm(boxes[t][1] - cam.cam_to_world[FRAME, :3, 3]))
    origin = cam.cam_to_world[FRAME, :3, 3]
    assert sc.pick(origin, boxes[car][1] - origin, FRAME) == car
    assert sc.pick(origin, -(boxes[car][1] - origin), FRAME) != car
    viewer.select(car)
    assert car in viewer.gui_actor_info.content and sc.actors[car].class_name in viewer.gui_actor_info.content

    base = sc.render(camera, FRAME)
    with torch.no_grad():  # no edits: exactly the reconstruction's render
        np.testing.assert_allclose(base, recon.render(camera, recon.time(FRAME)).rgb.clamp(0, 1).numpy(), atol=1e-6)

    # hide, through the panel's Visible checkbox of the selected car
    viewer.gui_actor_visible.value = False
    viewer._edit_selected()  # what the checkbox's callback runs (idempotent)
    assert sc.edits.get(car).hidden
    assert viewer.wait_idle()
    assert f"/actors/rigid/{car}" not in viewer._handles
    assert car not in sc.actor_boxes(FRAME)
    hidden = sc.render(camera, FRAME)
    np.testing.assert_allclose(hidden, sim_rgb(recon, camera, FRAME, Scenario((SimActorEdit(car, remove=True),))),
                               atol=1e-6)
    changed = np.abs(hidden - base).max(axis=-1) > 1e-4
    assert changed.any()
    # pixels change only where cars are drawn (the alpha footprint of the rigid node)
    with torch.no_grad():
        cars = recon.render(camera, recon.time(FRAME), hidden=frozenset({"background", "smpl", "sky"}))
    assert not (changed & ~(cars.alpha[..., 0].numpy() > 1e-4)).any()

    # move and turn the car, move a pedestrian: the same pixels and poses as the simulation
    viewer.edit_actor(car, ActorEdit(offset=(0.5, -0.4, 0.3), yaw=30.0))
    viewer.edit_actor(ped, ActorEdit(offset=(0.0, 1.5, 0.0), yaw=-45.0))
    assert viewer.wait_idle()
    scenario = Scenario((SimActorEdit(car, placement=Placement(offset_world=(0.5, -0.4, 0.3), yaw=30.0)),
                         SimActorEdit(ped, placement=Placement(offset_world=(0.0, 1.5, 0.0), yaw=-45.0))))
    moved = sc.render(camera, FRAME)
    np.testing.assert_allclose(moved, sim_rgb(recon, camera, FRAME, scenario), atol=1e-6)
    assert np.abs(moved - base).max() > 1e-3
    assert_placed_like_the_sim(viewer, Simulation(recon, scenario), FRAME)
    handle, _ = viewer._handles[f"/actors/rigid/{car}"]
    np.testing.assert_allclose(handle.position, boxes[car][1] + [0.5, -0.4, 0.3], atol=1e-5)
    np.testing.assert_allclose(sc.actor_boxes(FRAME)[car][1], boxes[car][1] + [0.5, -0.4, 0.3], atol=1e-5)
    # the panel shows the selected car's edit
    viewer.select(car)
    assert viewer.gui_actor_visible.value and viewer.gui_actor_yaw.value == 30.0
    viewer.reset_edits()
    assert viewer.wait_idle()
    np.testing.assert_allclose(sc.render(camera, FRAME), base, atol=1e-6)


SCENARIO = """# the viewer's scenario test
[[actor]]
track = "car_000"
remove = true

[[actor]]
track = "car_001"
stop_at = 0.3
brake = 0.1

[[actor]]
track = "pedestrian_013"
trajectory = [{{t = 0.0, x = 14.0, y = -6.0}}, {{t = 0.7, x = 14.0, y = -2.0}}]
motion = "gait"

[[insert]]
id = "guest"
run = "{run}"
track = "car_002"
trajectory = [[0.0, 20.0, 3.0, -1.1], [0.7, 26.0, 3.0, -1.1]]
"""


def test_scenario_drives_the_view(tiny_run, recon, plugins, tmp_path):
    """``omnire view --scenario``: removals, a stop, a new trajectory with a gait and an
    inserted actor follow the time slider in the browser objects, and the server render
    is the simulation's; the panel's edits apply on top."""
    path = tmp_path / "scenario.toml"
    path.write_text(SCENARIO.format(run=tiny_run.as_posix()))
    scenario = load_scenario(path)
    sim = Simulation(recon, scenario, plugins)
    sc = ViewerScene(recon, scenario=scenario, plugins=plugins)
    assert "car_000" not in sc.actors and sc.actors["guest"].inserted
    viewer = Viewer(sc, "127.0.0.1", 0, frame=1.0, verbose=False)
    try:
        camera = recon.camera(recon.scene.views([1])[0])
        versions = {}
        for frame in (1.0, 3.0, 6.0):
            viewer.gui_frame.value = frame
            viewer._dirty.set()
            assert viewer.wait_idle()
            assert_placed_like_the_sim(viewer, sim, frame)
            t = frame * 0.1
            np.testing.assert_allclose(viewer._handles["/actors/insert/guest"][0].position,
                                       [20.0 + 6.0 * t / 0.7, 3.0, -1.1], atol=1e-4)
            np.testing.assert_allclose(viewer._handles["/actors/smpl/pedestrian_013"][0].position[:2],
                                       [14.0, -6.0 + 4.0 * t / 0.7], atol=1e-4)
            versions[frame] = viewer._handles["/actors/smpl/pedestrian_013"][1]
            rgb = sc.render(camera, frame)
            np.testing.assert_allclose(rgb, sim.render(camera, recon.time(frame)).rgb.clamp(0, 1).numpy(), atol=1e-6)
            with torch.no_grad():
                recorded = recon.render(camera, recon.time(frame)).rgb.clamp(0, 1).numpy()
            print(f"frame {frame}: simulated vs recorded max abs diff {np.abs(rgb - recorded).max():.3f}")
            assert np.abs(rgb - recorded).max() > 1e-2, "the edits are in view"
        assert len(set(versions.values())) == 3, "the walking pedestrian is re-skinned as time moves"
        stopped = [sc.actor_boxes(f)["car_001"][1] for f in (3.0, 6.0)]
        np.testing.assert_allclose(stopped[0], stopped[1], atol=1e-6)  # stopped at 0.3 s
        assert np.abs(sc.actor_boxes(6.0)["car_003"][1] - sc.actor_boxes(3.0)["car_003"][1]).max() > 0.5

        # the panel's edits go on top of the scenario
        viewer.edit_actor("pedestrian_013", ActorEdit(offset=(0.0, 1.0, 0.0)))
        viewer.edit_actor("guest", ActorEdit(hidden=True))
        assert viewer.wait_idle()
        assert "/actors/insert/guest" not in viewer._handles
        np.testing.assert_allclose(viewer._handles["/actors/smpl/pedestrian_013"][0].position[:2],
                                   [14.0, -6.0 + 4.0 * 0.6 / 0.7 + 1.0], atol=1e-4)
        on_top = sc.edits.scenario(scenario)
        assert [i.id for i in on_top.inserts] == []
        assert_placed_like_the_sim(viewer, Simulation(recon, on_top, plugins), 6.0)
    finally:
        viewer.close()


def test_bad_scenario_is_one_line_and_exit_2(tiny_run, tmp_path, capsys):
    """Scenario errors are the simulation's own (line and field named), printed by the
    command line as one line, exit status 2: a malformed file before anything is loaded, a
    track the scene does not have once it is."""
    from omnire.cli import main as omnire_main

    for text, needles in (('[[actor]]\ntrack = "car_000"\nremov = true\n', ("line 3", "remov")),
                          ('\n[[actor]]\ntrack = "nobody"\nremove = true\n', ("line 3", "'track'", "nobody"))):
        bad = tmp_path / "bad.toml"
        bad.write_text(text)
        code = omnire_main(["view", str(tiny_run), "--scenario", str(bad), "--port", "0", "--seconds", "1"])
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if line.startswith("error:")]
        assert code == 2, err
        assert len(errors) == 1 and all(n in errors[0] for n in needles), err
        assert "bad.toml" in errors[0] and "Traceback" not in err


def test_training_observer_shows_snapshots(recon, plugins):
    """The registered observer, built the way the trainer builds it, shows copies: the
    trained model is never touched and updates reach the viewer at on_step."""
    trainer = SimpleNamespace(recon=recon, run_dir=None, config=SimpleNamespace(
        method_name="omnire", trainer=SimpleNamespace(observe_every=1)))
    observer = plugins.train_observers.get("viewer").factory(trainer, {"port": "0"})
    try:
        shown = observer.viewer.scene.recon
        assert shown is not recon and shown.model is not recon.model
        key = "nodes.background.gaussian_params.means"
        original = recon.model.state_dict()[key].clone()
        shown.model.state_dict()[key].add_(1.0)  # the viewer's copy is independent ...
        assert torch.equal(recon.model.state_dict()[key], original)  # ... of the model being trained
        observer.on_step(7, {"loss": 0.5, "psnr": 20.0})
        assert observer.viewer.scene.recon is not shown and "PSNR 20.00" in observer.viewer.gui_info.content
        assert torch.equal(observer.viewer.scene.recon.model.state_dict()[key], original)
        assert observer.viewer.wait_idle()
        assert "/nodes/background" in observer.viewer._handles
    finally:
        observer.close()


def test_clear_errors(tiny_run, plugins, recon, tmp_path):
    empty = tmp_path / "run"
    (empty / "checkpoints").mkdir(parents=True)
    (empty / "run.json").write_text((tiny_run / "run.json").read_text())
    with pytest.raises(UserError, match="no checkpoint"):
        view_main([str(empty)], plugins)
    with pytest.raises(UserError, match="no such run directory"):
        view_main([str(tmp_path / "missing")], plugins)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        t0 = time.monotonic()
        with pytest.raises(PortInUseError, match=f"127.0.0.1:{port} is already in use"):
            view_main([str(tiny_run), "--port", str(port)], plugins)
        assert time.monotonic() - t0 < 5, "a busy port is reported before the scene is loaded"
        with pytest.raises(PortInUseError):
            Viewer(ViewerScene(recon), "127.0.0.1", port, verbose=False)


def test_view_command_serves_the_page(tiny_run, plugins, tmp_path):
    """``omnire view --scenario`` end to end: loads the run and the scenario, serves the
    viewer's page on the port asked for, and stops after --seconds."""
    import threading
    import urllib.request

    scenario = tmp_path / "scenario.toml"
    scenario.write_text('[[actor]]\ntrack = "car_000"\nremove = true\n[[actor]]\ntrack = "car_001"\nstop_at = 0.2\n')

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault("code", view_main(
        [str(tiny_run), "--port", str(port), "--seconds", "4", "--frame", "1.5", "--scenario", str(scenario)],
        plugins)))
    thread.start()
    page, deadline = None, time.monotonic() + 30
    while page is None and time.monotonic() < deadline and thread.is_alive():
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
                page = r.read().decode("utf-8", "replace")
        except OSError:
            time.sleep(0.1)
    thread.join(30)
    assert page is not None and "<html" in page.lower()
    assert result.get("code") == 0


# ---------------------------------------------------------------------------- LiDAR
def sweep_xyz(points: np.ndarray) -> np.ndarray:
    return np.stack([points["x"], points["y"], points["z"]], axis=-1).astype(np.float64)


@pytest.fixture(scope="module")
def lidar_recon(tiny_lidar_run, plugins):
    torch.set_num_threads(1)
    return Reconstruction.from_run(tiny_lidar_run, plugins)


@pytest.fixture()
def lidar_viewer(lidar_recon):
    with opened(lidar_recon) as v:
        yield v


def test_ramp_colours_are_the_anchors_linearly_interpolated():
    from omnire_viewer.lidar import RAMP, ramp_colours

    got = ramp_colours(np.array([0.0, 0.25, 0.5, 0.75, 1.0, 0.125, -3.0, 7.0, np.nan]))
    np.testing.assert_array_equal(got[:5], RAMP.astype(np.uint8))
    np.testing.assert_array_equal(got[5], ((RAMP[0] + RAMP[1]) / 2 + 0.5).astype(np.uint8))  # halfway
    np.testing.assert_array_equal(got[6], RAMP[0].astype(np.uint8))  # clipped below
    np.testing.assert_array_equal(got[7], RAMP[-1].astype(np.uint8))  # and above
    np.testing.assert_array_equal(got[8], RAMP[0].astype(np.uint8))  # NaN: as 0


def test_the_rendered_sweep_follows_time_toggles_and_edits(lidar_viewer, lidar_recon):
    """Ticked, the viewer draws the sweep omnire sim renders of the same simulated scene at
    the slider's moment (``sim_sweep``), coloured by intensity or range; the time slider and
    the actor edits render it again (the node toggles only hide splats); unticked, it is
    hidden."""
    from omnire_sim.cli import sim_sweep
    from omnire_viewer.lidar import ramp_colours

    v = lidar_viewer
    assert v.scene.renders_lidar and not v.gui_lidar.disabled and v._lidar_handle is None  # off by default
    v.gui_lidar.value = True
    v._dirty.set()
    assert v.wait_idle()
    expected = sim_sweep(Simulation(lidar_recon, Scenario()), lidar_recon.time(FRAME))
    handle = v._lidar_handle
    assert len(expected) > 1000 and handle.visible
    np.testing.assert_allclose(handle.points, sweep_xyz(expected), atol=1e-4)
    np.testing.assert_array_equal(handle.colors, ramp_colours(expected["intensity"]))
    assert f"{len(expected):,} points at frame {FRAME:.1f}" in v.gui_lidar_note.content

    # By range: the same points, darker when nearer the sensor (viridis' green rises monotonically).
    v.gui_lidar_colour.value = "range"
    v._dirty.set()
    assert v.wait_idle()
    handle = v._lidar_handle
    np.testing.assert_allclose(handle.points, sweep_xyz(expected), atol=1e-4)
    sensor = sensor_path(lidar_recon.scene).at(lidar_recon.time(FRAME).seconds)[0, :3, 3]
    distance = np.linalg.norm(sweep_xyz(expected) - sensor, axis=1)
    green = handle.colors[np.argsort(distance), 1].astype(int)
    # ranges measured from the sensor of each ray's time (it moves during the sweep): near-monotonic here
    assert np.mean(np.diff(green) >= 0) > 0.95 and green[0] < 60 and green[-1] > 200
    assert "range 0 (dark) to" in v.gui_lidar_note.content

    # Another moment: another sweep (the sensor and the actors moved).
    v.gui_frame.value = float(FRAME + 3)
    v._dirty.set()
    assert v.wait_idle()
    later = sim_sweep(Simulation(lidar_recon, Scenario()), lidar_recon.time(FRAME + 3))
    np.testing.assert_allclose(v._lidar_handle.points, sweep_xyz(later), atol=1e-4)
    assert len(later) != len(expected) or np.abs(sweep_xyz(later) - sweep_xyz(expected)).max() > 0.1

    # The node toggles hide splats, not returns: the same sweep with the background's splats off.
    v.gui_nodes["background"].value = False
    v._dirty.set()
    assert v.wait_idle()
    np.testing.assert_allclose(v._lidar_handle.points, sweep_xyz(later), atol=1e-4)
    v.gui_nodes["background"].value = True

    # An actor hidden through the panel: the sweep of the simulation with that removal.
    tid = next(t for t, info in v.scene.actors.items() if info.node == "rigid")
    v.edit_actor(tid, ActorEdit(hidden=True))
    assert v.wait_idle()
    scenario = v.scene.edits.scenario(v.scene.base)
    removed = sim_sweep(Simulation(lidar_recon, scenario), lidar_recon.time(FRAME + 3))
    np.testing.assert_allclose(v._lidar_handle.points, sweep_xyz(removed), atol=1e-4)
    assert len(removed) != len(later) or np.abs(sweep_xyz(removed) - sweep_xyz(later)).max() > 0.1

    v.gui_lidar.value = False
    v._dirty.set()
    assert v.wait_idle()
    assert not v._lidar_handle.visible


def test_a_run_without_lidar_offers_no_sweep(viewer):
    """The tiny run learned no LiDAR: the box is disabled and says why; ticked anyway (a
    client that ignores the disabled flag), it is refused and nothing is drawn."""
    assert not viewer.scene.renders_lidar and viewer.gui_lidar.disabled
    assert "--method.lidar.enabled" in viewer.gui_lidar_note.content
    viewer.gui_lidar.value = True
    viewer._lidar_toggled(SimpleNamespace(client=None))
    assert viewer.wait_idle()
    assert viewer.gui_lidar.value is False and viewer._lidar_handle is None
    assert viewer.refusals[-1] == "Rendered sweep: this run learned no LiDAR"


@pytest.mark.skipif(find_chromium() is None, reason="headless browser test: no chromium on PATH "
                    "(Debian: apt-get install chromium; .ci/run installs it)")
def test_browser_draws_the_sweep(lidar_viewer, lidar_recon, tmp_path):
    """From above, with every node, box and camera switched off, the page shows the sweep
    alone: coloured points where they project, blank where none does; coloured by range,
    other colours on the same places; unticked, blank."""
    import imageio.v3 as iio

    v = lidar_viewer
    for box in (*v.gui_nodes.values(), v.gui_boxes, v.gui_cameras):
        box.value = False
    v.gui_lidar.value = True
    v._dirty.set()
    assert v.wait_idle()
    points = v._lidar_handle.points.astype(np.float64)
    sensor = sensor_path(lidar_recon.scene).at(lidar_recon.time(FRAME).seconds)[0]
    W, H = 360, 240
    # a camera 40 m above the sensor looking straight down, image up = the sensor's forward
    c2w = np.eye(4)
    forward = sensor[:3, 0] / np.linalg.norm(sensor[:3, 0])
    c2w[:3, 2] = (0.0, 0.0, -1.0)
    c2w[:3, 1] = -forward  # OpenCV y points down the image
    c2w[:3, 0] = np.cross(c2w[:3, 1], c2w[:3, 2])
    c2w[:3, 3] = sensor[:3, 3] + (0.0, 0.0, 40.0)
    f = 0.5 * H / math.tan(0.5 * math.radians(60.0))
    K = np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    with HeadlessChromium(width=W, height=H) as browser:
        client = page_client(browser, v)
        # Where the points project (12x12 blocks holding at least 3 of them) against blocks with none.
        w2c = np.linalg.inv(c2w)
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        uv = (p @ K.T)[:, :2] / p[:, 2:3]
        inside = (p[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        counts = np.zeros((H // 12, W // 12))
        np.add.at(counts, ((uv[inside, 1] // 12).astype(int), (uv[inside, 0] // 12).astype(int)), 1)
        for _attempt in range(4):  # a screenshot can precede the camera move's arrival: look again
            v.look_through(client, c2w, K, H)
            assert browser.evaluate(SHOW_ONLY_CANVAS) == [W, H]
            shot = settled_screenshot(browser, drawn=True)
            background = np.median(shot.reshape(-1, 3), axis=0)
            change = np.abs(blocks(shot, 12) - background).sum(axis=-1)
            if change[counts >= 3].mean() > 5 * max(change[counts == 0].mean(), 0.01):
                break
            time.sleep(1.0)
        iio.imwrite(tmp_path / "lidar_browser.png", (shot * 255).astype(np.uint8))
        print(f"blocks with points: {(counts >= 3).sum()}, mean change there {change[counts >= 3].mean():.3f}, "
              f"without any point {change[counts == 0].mean():.3f}")
        assert (counts >= 3).sum() > 20
        assert change[counts >= 3].mean() > 5 * max(change[counts == 0].mean(), 0.01)
        # coloured by range instead: the same points, other colours
        v.gui_lidar_colour.value = "range"
        v._dirty.set()
        assert v.wait_idle()
        by_range = settled_screenshot(browser, drawn=True)
        iio.imwrite(tmp_path / "lidar_browser_range.png", (by_range * 255).astype(np.uint8))
        # The browser redrew the points in their new colours (which colours: the test above):
        # blocks holding points changed, blocks without any did not.
        recoloured = np.abs(blocks(by_range, 12) - blocks(shot, 12)).sum(axis=-1)
        assert recoloured[counts >= 3].mean() > 5 * max(recoloured[counts == 0].mean(), 1e-4)
        v.gui_lidar.value = False
        v._dirty.set()
        assert v.wait_idle()
        empty = settled_screenshot(browser, drawn=False)
        assert empty.std() < 0.02 and np.abs(empty - shot).mean() > 0.01
