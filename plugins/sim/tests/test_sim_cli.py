"""``omnire sim`` and ``omnire render --video`` on a tiny trained run (conftest.demo_run):
frames, videos and manifest written atomically outside the run; bad input refused before
anything is written."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from omnire.api import Reconstruction, UserError, View
from omnire.io.video import read_mp4
from omnire.model import ENVIRONMENT_MIN_TRANSMITTANCE
from omnire_sim.cli import SimArgs, run_sim


def write(tmp: Path, text: str, name: str = "scenario.toml") -> Path:
    path = tmp / name
    path.write_text(text)
    return path


def read_png(path: Path) -> np.ndarray:
    img = oiio.ImageInput.open(str(path))
    data = img.read_image(format=oiio.UINT8)
    img.close()
    return data


def snapshot(path: Path) -> dict:
    return {p: p.stat().st_mtime_ns for p in sorted(path.rglob("*"))}


@pytest.fixture(scope="module")
def recon(demo_run, plugins):
    return Reconstruction.from_run(demo_run, plugins)


def test_empty_scenario_writes_recorded_frames_video_and_manifest(demo_run, recon, plugins, tmp_path):
    before = snapshot(demo_run)
    out = tmp_path / "out"
    run_sim(SimArgs(demo_run, write(tmp_path, "# nothing changed\n"), out, progress=False), plugins)
    manifest = json.loads((out / "manifest.json").read_text())
    scene = recon.scene
    names = [c.name for c in scene.cameras]
    assert manifest["camera_path"]["cameras"] == names and manifest["camera_path"]["frames"] == scene.num_frames
    assert "PandaSet" in manifest["attribution"]
    for f in range(scene.num_frames):
        for c, name in enumerate(names):
            got = read_png(out / manifest["frames"][f]["cameras"][name]["image"])
            with torch.no_grad():  # the inference path, as the simulator renders
                rgb = recon.render(recon.camera(View(c, f)), recon.time(f)).rgb
            expect = (np.clip(rgb.detach().numpy(), 0, 1) * 255 + 0.5).astype(np.uint8)
            assert np.array_equal(got, expect)
    frames, fps = read_mp4(out / f"{names[0]}.mp4")
    assert frames.shape[0] == scene.num_frames and fps == pytest.approx(10.0, rel=0.02)
    w, h = scene.cameras[0].width, scene.cameras[0].height
    assert frames.shape[1:3] == (h + h % 2, w + w % 2)
    assert snapshot(demo_run) == before  # nothing written into the run
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_edits_interpolated_path_depth_alpha(demo_run, recon, plugins, tmp_path):
    track = recon.assignment["rigid"][0]
    text = f"""
[camera]
path = "interpolated"
fps = 20
cameras = ["front_camera"]
[[camera.lane_shift]]
offset = 1.0
start = 0.1
end = 0.2
[output]
depth = true
alpha = true
[[actor]]
track = "{track}"
remove = true
"""
    out = tmp_path / "out"
    run_sim(SimArgs(demo_run, write(tmp_path, text), out, progress=False, fps=5.0), plugins)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["camera_path"]["frames"] == 6 and manifest["outputs"]["video_fps"] == 5.0
    assert manifest["actors"] == [{"id": track, "kind": "removed", "node": "rigid"}]
    for f in manifest["frames"]:
        entry = f["cameras"]["front_camera"]
        for key in ("image", "depth", "alpha"):
            assert (out / entry[key]).is_file()
    shift = np.array(manifest["frames"][-1]["cameras"]["front_camera"]["cam_to_world"])[:3, 3] - \
        np.array(manifest["frames"][0]["cameras"]["front_camera"]["cam_to_world"])[:3, 3]
    assert np.linalg.norm(shift) > 0.9
    frames, fps = read_mp4(out / "front_camera.mp4")
    assert len(frames) == 6 and fps == pytest.approx(5.0)
    assert not (out / "front_left_camera.mp4").exists()


def test_existing_output_refused_unless_overwrite(demo_run, plugins, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    scenario = write(tmp_path, '[camera]\nframes = [0]\ncameras = ["front_camera"]\n')
    with pytest.raises(UserError, match="already exists"):
        run_sim(SimArgs(demo_run, scenario, out, progress=False), plugins)
    assert (out / "keep.txt").is_file()
    with pytest.raises(UserError, match="lies inside"):
        run_sim(SimArgs(demo_run, scenario, demo_run / "sim", progress=False), plugins)
    # --overwrite replaces only omnire sim's own output (omnire/io/outputs.py)
    with pytest.raises(UserError, match="not written by omnire sim"):
        run_sim(SimArgs(demo_run, scenario, out, overwrite=True, progress=False, video=False), plugins)
    assert (out / "keep.txt").read_text() == "mine"
    (out / "keep.txt").unlink()
    run_sim(SimArgs(demo_run, scenario, out, overwrite=True, progress=False, video=False), plugins)
    assert (out / "front_camera" / "00000.png").is_file()
    run_sim(SimArgs(demo_run, scenario, out, overwrite=True, progress=False, video=False), plugins)
    assert (out / "front_camera" / "00000.png").is_file()


@pytest.mark.parametrize("kind", ["unknown track", "time outside the log", "malformed trajectory", "no checkpoint",
                                  "unreadable asset run", "bad camera"])
def test_bad_input_fails_clearly_and_writes_nothing(kind, demo_run, recon, plugins, tmp_path):
    track = recon.assignment["rigid"][0]
    run = demo_run
    asset = tmp_path / "asset"
    asset.mkdir()
    (asset / "run.json").write_text("{not json")
    texts = {
        "unknown track": ('[[actor]]\ntrack = "no-such-car"\nremove = true\n', "no track 'no-such-car'"),
        "time outside the log": (f'[[actor]]\ntrack = "{track}"\nstop_at = 99.0\n', "outside the log"),
        "malformed trajectory": (f'[[actor]]\ntrack = "{track}"\ntrajectory = [[0.0, 1.0]]\n', "[t, x, y]"),
        "no checkpoint": ("", "no checkpoints"),
        "unreadable asset run": (f'[[insert]]\nid = "g"\nrun = "asset"\ntrack = "{track}"\n'
                                 'trajectory = [[0.0, 1.0, 2.0, 0.5]]\n', "asset run"),
        "bad camera": ('[camera]\npath = "interpolated"\nfps = 10\nstart = 0.0\nend = 50.0\n',
                       "line 5, [camera], field 'end'"),
    }
    text, needle = texts[kind]
    if kind == "no checkpoint":
        run = tmp_path / "empty-run"
        run.mkdir()
        shutil.copy(demo_run / "run.json", run / "run.json")
    out = tmp_path / "out"
    with pytest.raises(UserError) as err:
        run_sim(SimArgs(run, write(tmp_path, text), out, progress=False), plugins)
    assert needle in str(err.value)
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_insert_from_another_run_directory(demo_run, recon, plugins, tmp_path):
    other = tmp_path / "other-run"
    shutil.copytree(demo_run, other)
    track = recon.assignment["rigid"][0]
    text = (f'[camera]\nframes = [1]\ncameras = ["front_camera"]\n[[insert]]\nid = "guest"\nrun = "other-run"\n'
            f'track = "{track}"\ntrajectory = [[0.0, 12.0, 0.0, -1.0]]\n')
    out = tmp_path / "out"
    run_sim(SimArgs(demo_run, write(tmp_path, text), out, progress=False, video=False, alpha=True), plugins)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["actors"][0]["kind"] == "inserted" and manifest["actors"][0]["track"] == track


def test_command_line(demo_run, tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200")
    bad = write(tmp_path, '[[actor]]\ntrack = "x"\nremov = true\n')
    res = subprocess.run([sys.executable, "-m", "omnire.cli", "sim", str(demo_run), "--scenario", str(bad),
                          "--output", str(tmp_path / "o")], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 2, res.stderr
    assert "line 3" in res.stderr and "remov" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "o").exists()
    out = tmp_path / "r"
    res = subprocess.run([sys.executable, "-m", "omnire.cli", "render", str(demo_run), "--split", "all", "--cameras",
                          "front_camera", "--video", "--fps", "20", "--output", str(out)],
                         capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    frames, fps = read_mp4(out / "front_camera.mp4")
    assert len(frames) == 6 and fps == pytest.approx(20.0)  # 0.2998 s of log at 20 fps
    assert len(list(out.glob("*.png"))) == 4


def test_video_writer_is_atomic(tmp_path):
    from omnire.io.video import Mp4Writer

    target = tmp_path / "v.mp4"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), Mp4Writer(target, fps=10) as video:
        video.append(torch.zeros(8, 8, 3))
        raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["v.mp4"]
    with Mp4Writer(target, fps=10) as video:
        for i in range(3):
            video.append(np.full((9, 11, 3), i * 100, np.uint8))
    frames, fps = read_mp4(target)
    assert frames.shape == (3, 10, 12, 3) and fps == 10.0
    assert abs(int(frames[2, 4, 4, 0]) - 200) <= 3


def test_video_is_h264(tmp_path):
    import imageio_ffmpeg

    from omnire.io.video import write_mp4

    write_mp4(tmp_path / "v.mp4", [np.zeros((16, 16, 3), np.uint8)] * 2, fps=5)
    meta = next(imageio_ffmpeg.read_frames(str(tmp_path / "v.mp4")))
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")


def test_bench_render(demo_run, plugins, tmp_path):
    from omnire_sim.bench import main

    args = [str(demo_run), "--resolutions", "64x36", "--views", "2", "--warmup", "1", "--threads", "1"]
    assert main([*args, "--output", str(tmp_path / "a"), "--save-images", str(tmp_path / "ref")], plugins) == 0
    assert main([*args, "--output", str(tmp_path / "b"), "--compare-to", str(tmp_path / "ref"), "--profile"],
                plugins) == 0
    result = json.loads((tmp_path / "b" / "results.json").read_text())[0]
    size = result["sizes"]["64x36"]
    assert result["method"] == "streetgs" and result["views"] == 2 and result["peak_mb"] > 0
    assert size["fps"] > 0 and size["max_abs_diff"] == 0.0
    assert "| demo | streetgs |" in (tmp_path / "b" / "results.md").read_text()
    # where the time went: every stage measured, the render's stages within its mean time
    stages = size["stages_ms"]
    assert {"nodes", "raster.rows", "raster.depth_order", "raster.binning", "raster.compositing", "raster.other",
            "environment", "other", "png"} <= set(stages)
    assert all(v >= 0 for v in stages.values()) and stages["raster.compositing"] > 0
    assert sum(v for k, v in stages.items() if k != "png") <= 1.01 * 1000 / size["fps"]
    # the inference path against the training path's pixels (autograd on)
    assert main([*args, "--output", str(tmp_path / "c"), "--training-path", "--save-images", str(tmp_path / "train")],
                plugins) == 0
    training = json.loads((tmp_path / "c" / "results.json").read_text())[0]
    assert training["path"] == "training" and training["sizes"]["64x36"]["sky_fraction"] == 1.0
    assert main([*args, "--output", str(tmp_path / "d"), "--compare-to", str(tmp_path / "train")], plugins) == 0
    inference = json.loads((tmp_path / "d" / "results.json").read_text())[0]["sizes"]["64x36"]
    # rounding, and the sky left out where the Gaussians leave it a transmittance <= 1e-3
    assert 0.0 <= inference["max_abs_diff"] <= 1e-4 + ENVIRONMENT_MIN_TRANSMITTANCE
    assert 0.0 < inference["sky_fraction"] <= 1.0
    # a rig (every camera of the views' frames, side by side on two threads): the single renders' pixels
    rig = [str(demo_run), "--resolutions", "64x36", "--views", "2", "--warmup", "1", "--threads", "2", "--rig"]
    assert main([*rig, "--output", str(tmp_path / "e"), "--save-images", str(tmp_path / "rig")], plugins) == 0
    got = json.loads((tmp_path / "e" / "results.json").read_text())[0]
    saved = [p.stem.rsplit("_", 1) for p in (tmp_path / "rig").rglob("*.npy")]  # (camera, frame) of each image
    cameras, frames = {c for c, _ in saved}, {f for _, f in saved}
    assert got["rig"] and got["views"] == len(saved) == len(cameras) * len(frames) and len(cameras) >= 2
    assert " (rig) |" in (tmp_path / "e" / "results.md").read_text()
    assert main([*args, "--output", str(tmp_path / "f"), "--compare-to", str(tmp_path / "rig")], plugins) == 0
    assert json.loads((tmp_path / "f" / "results.json").read_text())[0]["sizes"]["64x36"]["max_abs_diff"] == 0.0
