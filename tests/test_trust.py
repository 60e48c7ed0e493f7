"""What the framework reads and reports can be trusted: ego-vehicle masks, run directories
that never mix, checkpoints chosen and checked, interruptions, portable run.json,
divergence reports, file permissions and full tables (issue: trust what it reads)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from omnire.io.atomic import atomic_write_bytes
from omnire.losses import LossContext, dssim_loss, l1_loss, lidar_inverse_depth_loss
from omnire.method import MethodConfig
from omnire.nodes.background import BackgroundConfig
from omnire.plugins import load_plugins
from omnire.rundir import RunDirectory, RunDirectoryError
from omnire.strategy import DensifyConfig
from omnire.trainer import TrainConfig, Trainer, TrainerConfig

from scene_helpers import DEMO_SCENE, REPO

SHARED = REPO.parent / "shared" / "data" / "pandaset" / "002"
OMNIRE = [sys.executable, "-m", "omnire.cli"]


def tiny_method(lr_scale: float = 1.0) -> MethodConfig:
    bg = BackgroundConfig(voxel_size=0.5, num_far_points=200)
    for name in ("lr_means", "lr_means_final", "lr_sh0", "lr_shN", "lr_opacity", "lr_scales", "lr_quats"):
        setattr(bg, name, getattr(bg, name) * lr_scale)
    return MethodConfig(nodes={"background": bg}, densify=DensifyConfig(refine_start=10**6), sh_degree_interval=15,
                        rasterizer="torch")


def trainer(scene, tmp_path, steps=20, name="run", lr_scale=1.0, **kw):
    tc = TrainerConfig(max_steps=steps, output_dir=tmp_path, run_name=name, log_every=5, progress=False,
                       eval_train_views=0, **kw)
    return Trainer(TrainConfig("3dgs", "test", tiny_method(lr_scale), None, tc), load_plugins(), argv=[], scene=scene)


# ---------------------------------------------------------------------------------- ego masks
def test_losses_ignore_the_ego_vehicles_pixels():
    g = torch.Generator().manual_seed(0)
    rgb, target = torch.rand(24, 32, 3, generator=g), torch.rand(24, 32, 3, generator=g)
    scene = torch.ones(24, 32, 1)
    scene[16:] = 0  # the car's body in the lower third
    other = target.clone()
    other[16:] = 1 - other[16:]  # anything at all where the car is
    for loss in (l1_loss, dssim_loss):
        a = loss(LossContext(rgb, rgb[..., :1], rgb[..., :1], target, scene_pixels=scene))
        b = loss(LossContext(rgb, rgb[..., :1], rgb[..., :1], other, scene_pixels=scene))
        if loss is l1_loss:
            torch.testing.assert_close(a, b)
        else:  # SSIM windows reach 5 px across the edge of the mask: only there may it differ
            assert abs(float(a - b)) < 0.05 * float(a)
        assert float(loss(LossContext(rgb, rgb[..., :1], rgb[..., :1], other))) != float(b)
    depth = torch.full((24, 32, 1), 5.0)
    pix = torch.tensor([3 * 32 + 4, 20 * 32 + 4])  # one scene pixel, one on the car
    d = lidar_inverse_depth_loss(LossContext(rgb, depth, depth, target, lidar_pixels=pix,
                                             lidar_depth=torch.tensor([5.0, 0.5]), scene_pixels=scene))
    assert float(d) == 0.0  # the return on the car is not used


def test_estimated_ego_mask_finds_a_static_body_and_nothing_on_moving_views():
    from omnire.egomask import estimate_ego_mask

    from scipy import ndimage

    rng = np.random.default_rng(0)
    T, H, W = 12, 60, 80
    world = ndimage.gaussian_filter(rng.random((H, W + 4 * T, 3)), (2, 2, 0))  # a street's blobs, not pixel noise
    world = (world - world.min()) / (world.max() - world.min())
    frames = np.stack([world[:, 4 * t:4 * t + W] for t in range(T)])  # the world slides past
    with_car = frames.copy()
    body = np.zeros((H, W), bool)
    body[45:] = True
    body[38:45, 30:50] = True  # an antenna fin
    shade = np.linspace(0.75, 0.9, H)[:, None, None] * np.ones((H, W, 3))
    with_car[:, body] = shade[body]  # the same smooth body in every frame
    mask = estimate_ego_mask(with_car)
    iou = (mask & body).sum() / (mask | body).sum()
    assert iou > 0.9, iou
    assert not estimate_ego_mask(frames).any()


@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data/pandaset/002 not present")
def test_pandaset_back_camera_mask_matches_the_estimate_and_front_cameras_have_none():
    import OpenImageIO as oiio

    from omnire.data.images import ImageCache
    from omnire.egomask import estimate_scene_ego_masks
    from omnire_pandaset.dataparser import EGO_MASKS, PandasetConfig

    cfg = PandasetConfig(data=SHARED, cameras=("back_camera", "front_camera"), scale=0.25, holdout_every=0)
    scene = cfg.setup().parse()
    masks = estimate_scene_ego_masks(scene, ImageCache(), max_frames=20)
    shipped = oiio.ImageBuf(str(EGO_MASKS["back_camera"]))
    shipped = oiio.ImageBufAlgo.resize(shipped, roi=oiio.ROI(0, 240, 0, 135, 0, 1, 0, 1))
    shipped = np.asarray(shipped.get_pixels(oiio.FLOAT)).reshape(135, 240) > 0.5
    back = masks["back_camera"]
    assert (back & shipped).sum() / (back | shipped).sum() > 0.85
    assert 0.12 < shipped.mean() < 0.25 and not masks["front_camera"].any()


# ---------------------------------------------------------------------------------- run directories
def test_resume_continues_in_place_without_duplicated_metrics(tiny_scene, tmp_path):
    first = trainer(tiny_scene, tmp_path, steps=20, checkpoint_every=10)
    first.train()
    run = first.run_dir
    (run / "checkpoints" / "step-000020.pt").unlink()  # as if stopped after step 10's checkpoint
    resumed = trainer(tiny_scene, tmp_path, steps=20, checkpoint_every=10, name=None, resume=run)
    assert resumed.run_dir == run and resumed.step == 10
    resumed.train()
    steps = [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()
             if "loss" in json.loads(line)]
    assert steps == sorted(set(steps)) == [5, 10, 15, 20]


def test_newest_checkpoint_by_step_number_and_temporary_files_removed(tmp_path):
    run = RunDirectory(tmp_path / "r")
    state = {"step": 0, "model": {}}
    for step in (999999, 1000000, 20):
        state["step"] = step
        path = tmp_path / "r" / "checkpoints" / f"step-{step:06d}.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(state, path)
    leftover = run.checkpoint_dir / ".step-000030.pt.abcd.tmp"
    leftover.write_bytes(b"partial")
    path, loaded = run.load_latest_checkpoint()
    assert path.name == "step-1000000.pt" and loaded["step"] == 1000000  # text order would say 999999
    assert run.remove_temporary_files() == [leftover] and not leftover.exists()


def test_failed_checkpoint_write_is_one_line_and_keeps_the_previous_one(tiny_scene, tmp_path, monkeypatch):
    t = trainer(tiny_scene, tmp_path, steps=4, checkpoint_every=2)
    t.train()
    before = sorted(p.name for p in (t.run_dir / "checkpoints").iterdir())

    def disk_full(path, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("omnire.trainer.atomic_write_bytes", disk_full)
    with pytest.raises(RunDirectoryError, match=r"step-000004.pt: cannot write checkpoint \(No space left on device\)"):
        t.save_checkpoint()
    assert sorted(p.name for p in (t.run_dir / "checkpoints").iterdir()) == before


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_interrupt_writes_a_checkpoint_and_exits_non_zero(tmp_path):
    cmd = OMNIRE + ["train", "3dgs", "pandaset", "--data", str(DEMO_SCENE), "--end-frame", "4", "--scale", "0.25",
                    "--method.rasterizer", "torch", "--method.nodes.background.max-lidar-points", "2000",
                    "--method.nodes.background.num-far-points", "200", "--trainer.max-steps", "100000",
                    "--trainer.log-every", "1", "--trainer.no-progress", "--trainer.output-dir", str(tmp_path),
                    "--trainer.run-name", "r"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    metrics = tmp_path / "r" / "metrics.jsonl"
    deadline = time.time() + 300
    while time.time() < deadline and not (metrics.is_file() and metrics.read_text().count("\n") >= 3):
        time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "SIGINT: stopped at step" in err and "Traceback" not in err
    ckpts = list((tmp_path / "r" / "checkpoints").glob("step-*.pt"))
    assert len(ckpts) == 1 and int(ckpts[0].stem.split("-")[1]) >= 3


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_run_json_is_portable(tmp_path):
    work = tmp_path / "work"
    shutil.copytree(DEMO_SCENE, work / "scene")
    train = OMNIRE + ["train", "3dgs", "pandaset", "--data", "scene", "--end-frame", "4", "--holdout-every", "2",
                      "--scale", "0.25", "--method.rasterizer", "torch", "--method.nodes.background.max-lidar-points",
                      "2000", "--method.nodes.background.num-far-points", "200", "--trainer.max-steps", "2",
                      "--trainer.no-progress", "--trainer.output-dir", "runs", "--trainer.run-name", "r"]
    out = subprocess.run(train, cwd=work, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    info = json.loads((work / "runs" / "r" / "run.json").read_text())
    assert str(work / "scene") in info["argv"]  # stored absolute
    out = subprocess.run(OMNIRE + ["eval", str(work / "runs" / "r")], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr
    assert "vehicle PSNR" in out.stdout  # tables printed in full into a pipe (no "vehi…")


# ---------------------------------------------------------------------------------- reports and files
def test_divergence_is_reported(tiny_scene, tmp_path):
    t = trainer(tiny_scene, tmp_path, steps=40, lr_scale=1000.0)
    result = t.train()
    assert any("looks diverged" in w or "fell to" in w for w in result.get("warnings", [])), result.get("warnings")
    final = [json.loads(line) for line in (t.run_dir / "metrics.jsonl").read_text().splitlines()][-1]
    assert final["final"] and final["eval"]["warnings"]


def test_written_files_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write_bytes(tmp_path / "a.bin", b"x")
        from omnire.io.images import write_png

        write_png(tmp_path / "a.png", np.zeros((2, 2, 3)))
    finally:
        os.umask(old)
    assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "a.png").stat().st_mode & 0o777 == 0o644
