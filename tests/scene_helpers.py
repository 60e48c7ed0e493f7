"""Test helpers: a tiny procedurally-made scene on disk (no ../shared needed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from omnire.data.scene import ActorTrack, CameraSequence, LidarSweeps, SceneData, holdout_split
from omnire.io.images import write_png

REPO = Path(__file__).resolve().parents[1]
DEMO_SCENE = REPO / "data" / "demo" / "pandaset_002"
# OpenCV camera looking along world +x with z up: columns are the camera axes in the world.
LOOK_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def make_tiny_scene(root: Path, frames: int = 6, width: int = 48, height: int = 32, holdout: int = 3,
                    with_track: bool = True) -> SceneData:
    """Two cameras driving along +x in front of a textured wall (x = 12) over a ground plane
    (z = -1.5). Images are the analytic texture seen by each camera; LiDAR samples both
    surfaces. Returns a validated SceneData whose images live under ``root``."""
    rng = np.random.default_rng(0)
    K = np.array([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]])
    cams = []
    for ci, yaw_off in enumerate([0.0, 0.15]):
        c, s = np.cos(yaw_off), np.sin(yaw_off)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        c2w = np.tile(np.eye(4), (frames, 1, 1))
        paths = []
        for f in range(frames):
            c2w[f, :3, :3] = Rz @ LOOK_X
            c2w[f, :3, 3] = [0.4 * f, 0.3 * ci, 0.0]
            img = _render_texture(c2w[f], K, width, height)
            path = root / f"cam{ci}" / f"{f:02d}.png"
            write_png(path, img)
            paths.append(path)
        cams.append(CameraSequence(f"cam{ci}", width, height, K, c2w, paths, np.arange(frames) * 0.1))
    pts = []
    for f in range(frames):
        wall = np.stack([np.full(800, 12.0), rng.uniform(-8, 8, 800), rng.uniform(-1.5, 4, 800)], 1)
        ground = np.stack([rng.uniform(1, 12, 800), rng.uniform(-8, 8, 800), np.full(800, -1.5)], 1)
        pts.append(np.concatenate([wall, ground]).astype(np.float32))
    pts[frames // 2] = None  # a real gap, as in PandaSet
    lidar = LidarSweeps(pts, np.zeros((frames, 3)))
    tracks = []
    if with_track:
        poses = np.tile(np.eye(4), (frames, 1, 1))
        poses[:, 0, 3] = 7.0 + 0.2 * np.arange(frames)
        poses[:, 2, 3] = -0.8
        tracks.append(ActorTrack("car-1", "Car", "vehicle", poses, np.array([4.0, 1.8, 1.5]),
                                 np.ones(frames, dtype=bool)))
    train, test = holdout_split(frames, holdout)
    return SceneData("tiny", cams, np.arange(frames) * 0.1, np.arange(frames), train, test, lidar, tracks).validate()


def _render_texture(c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Ray-cast the wall (x=12) and ground (z=-1.5) with a checker texture; sky above."""
    v, u = np.mgrid[0:height, 0:width] + 0.5
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = d_cam @ c2w[:3, :3].T
    o = c2w[:3, 3]
    img = np.zeros((height, width, 3))
    img[:] = [0.55, 0.7, 0.95]
    t_wall = np.where(d[..., 0] > 1e-6, (12.0 - o[0]) / np.maximum(d[..., 0], 1e-6), np.inf)
    t_ground = np.where(d[..., 2] < -1e-6, (-1.5 - o[2]) / np.minimum(d[..., 2], -1e-6), np.inf)
    hit_wall = (t_wall < t_ground) & np.isfinite(t_wall)
    p = o + d * np.minimum(t_wall, t_ground)[..., None]
    p_wall_top = p[..., 2] < 4.0
    checker_w = ((np.floor(p[..., 1]) + np.floor(p[..., 2])) % 2)[..., None]
    checker_g = ((np.floor(p[..., 0]) + np.floor(p[..., 1])) % 2)[..., None]
    wall_col = 0.25 + 0.5 * checker_w * np.array([1.0, 0.4, 0.2])
    ground_col = 0.2 + 0.3 * checker_g * np.array([0.5, 0.5, 0.5])
    img = np.where((hit_wall & p_wall_top)[..., None], wall_col, img)
    img = np.where((~hit_wall & np.isfinite(t_ground))[..., None], ground_col, img)
    return img


def assert_same_state(a: dict, b: dict) -> None:
    """Two model state dicts hold the same keys, shapes and values (resume tests)."""
    import torch

    assert a.keys() == b.keys()
    for k in a:
        if torch.is_tensor(a[k]):
            assert a[k].shape == b[k].shape, k
            torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6, msg=k)


def gaussians_at(node, frame, seconds=0.0, step=None, camera=None):
    """A node's (world Gaussians, rows) at a recorded frame, or None when it is absent."""
    from omnire.data.scene import SceneTime

    out = node.gaussians_at(SceneTime(frame, seconds), camera, step)
    return None if out is None else (out.gaussians, out.rows)


def regularization_at(node, frame, seconds=0.0, step=None):
    """A node's regularisers for what it renders at a recorded frame ({} when absent)."""
    from omnire.data.scene import SceneTime

    out = node.gaussians_at(SceneTime(frame, seconds), None, step)
    return {} if out is None else node.regularization(out)


TINY_RUN_KEY = "omnire-tiny-run-v1"  # bump when the recipe below changes
# method flags of the tiny run (also what a command must repeat to load it as the same run)
TINY_RUN_METHOD_ARGS = ["--method.rasterizer", "torch", "--method.nodes.background.max-lidar-points", "3000",
                        "--method.nodes.background.num-far-points", "300",
                        "--method.nodes.smpl.gaussians-per-person", "300"]


TINY_LIDAR_RUN_KEY = "omnire-tiny-lidar-run-v1"  # bump when the recipe of make_tiny_lidar_run changes
TINY_LIDAR_RUN_METHOD_ARGS = ["--method.rasterizer", "cpu", *TINY_RUN_METHOD_ARGS[2:], "--method.lidar.enabled",
                              "--method.lidar.rays-per-step", "2000"]


def make_tiny_lidar_run(root):
    """:func:`make_tiny_run` with LiDAR learning on (``TINY_LIDAR_RUN_METHOD_ARGS``: the
    native rasterizer, whose LiDAR path is fast enough to render whole sweeps in a test)."""
    return make_tiny_run(root, TINY_LIDAR_RUN_METHOD_ARGS)


def make_tiny_run(root, method_args=None):
    """A tiny trained OmniRe run (background, rigid cars, SMPL pedestrians, sky): ``omnire
    synth urban --tiny`` with one camera under ``root``, two training steps with
    ``method_args`` (default ``TINY_RUN_METHOD_ARGS``); returns the run directory (reused
    when ``root`` already holds it: one per test session, shared by the plugins' tests
    through the ``TINY_RUN_KEY`` folder)."""
    import os

    import torch

    from omnire.plugins import load_plugins
    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    run = root / "runs" / "omnire"
    if list((run / "checkpoints").glob("step-*.pt")):
        return run
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    plugins = load_plugins()
    scene = root / "scene"
    synth = plugins.commands.get("synth").main
    assert synth(["urban", str(scene), "--tiny", "--num-cameras", "1"], plugins) in (0, None)
    argv = ["omnire", "processed", "--data", str(scene), "--trainer.max-steps", "2",
            "--trainer.output-dir", str(root / "runs"), "--trainer.run-name", "omnire", "--trainer.no-progress",
            "--trainer.eval-train-views", "1", "--trainer.threads", "1",
            *(TINY_RUN_METHOD_ARGS if method_args is None else method_args)]
    Trainer(parse_train_args(argv, plugins), plugins, argv=argv).train()
    return run
