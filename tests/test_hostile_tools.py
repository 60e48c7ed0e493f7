"""Hostile inputs to the tools that write outputs (sim, export, render, batch): --overwrite
aimed at a dataset or a run, runaway sizes and rates, deeply nested files, outputs that
cannot be written, malformed numbers. Each case goes through the real CLI entry point (in
process) via tests/hostile.py and must end with a one-line error naming the field or path,
with every input unchanged and no partial output left (issue 41)."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from omnire.cli import main

from hostile import record, run_case
from scene_helpers import DEMO_SCENE

pytestmark = pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
TRAIN = ["--end-frame", "4", "--holdout-every", "2", "--scale", "0.25", "--method.rasterizer", "torch",
         "--method.nodes.background.max-lidar-points", "2000", "--method.nodes.background.num-far-points", "200",
         "--trainer.no-progress", "--trainer.eval-train-views", "1", "--trainer.max-steps", "2"]
DEEP = 150_000


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A copy of the demo scene and a 2-step 3dgs run trained on that copy (the copy is what
    a tool aimed at "the run's dataset" would destroy)."""
    root = tmp_path_factory.mktemp("hostile-tools")
    data = root / "scene"
    shutil.copytree(DEMO_SCENE, data)
    code = main(["train", "3dgs", "pandaset", "--data", str(data), *TRAIN, "--trainer.output-dir", str(root / "runs"),
                 "--trainer.run-name", "base"])
    assert code == 0
    return data, root / "runs" / "base"


def _scenario(tmp_path: Path, text: str, name: str = "scenario.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _sim(run: Path, scenario: Path, out: Path, *flags: str) -> list[str]:
    return ["sim", str(run), "--scenario", str(scenario), "--output", str(out), "--no-progress", "--max-frames", "1",
            "--no-video", *flags]


@contextlib.contextmanager
def _tiny_filesystem(path: Path, size: str = "8k"):
    """A real tmpfs of ``size`` at ``path`` (disk-full and read-only cases); skipped where
    this process may not mount."""
    path.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


# ------------------------------------------------------------------ 1. --overwrite deletes only its own
def test_overwrite_never_deletes_a_dataset_or_run(setup, tmp_path, capsys, monkeypatch):
    """Issue 41 item 1: sim/export/render/batch aimed at the run's dataset, the run, their
    parent, the current directory or a folder of someone else's files: refused, nothing lost."""
    data, run = setup
    empty = _scenario(tmp_path, "")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    inputs = [data, run, foreign]
    for name, out in [("dataset", data), ("run", run), ("run parent", run.parent), ("foreign folder", foreign)]:
        run_case(f"sim --overwrite into the {name}", _sim(run, empty, out, "--overwrite"), capsys, inputs,
                 needles=("--output",), surface="sim")
        run_case(f"export --per-node --overwrite into the {name}",
                 ["export", str(run), "--per-node", "--output", str(out), "--overwrite"], capsys, inputs,
                 needles=("--output",), surface="export")
    run_case("export a PLY into the dataset", ["export", str(run), "--output", str(data / "scene.ply")], capsys,
             inputs, needles=("--output",), surface="export")
    run_case("render into the dataset", ["render", str(run), "--frames", "0", "--output", str(data)], capsys, inputs,
             needles=("--output",), surface="render")
    run_case("render into the run directory itself", ["render", str(run), "--frames", "0", "--output", str(run)],
             capsys, inputs, needles=("--output",), surface="render")
    run_case("batch output is the dataset",
             ["batch", "--scenes", f"s=pandaset:{data}", "--methods", "3dgs", "--output", str(data), "--dry-run"],
             capsys, inputs, needles=("--output",), surface="batch")
    monkeypatch.chdir(foreign)
    run_case("sim --overwrite into the current directory", _sim(run, empty, Path("."), "--overwrite"), capsys,
             inputs, needles=("current directory",), surface="sim")
    run_case("sim --overwrite into a parent of the current directory", _sim(run, empty, tmp_path, "--overwrite"),
             capsys, inputs, needles=("current directory",), surface="sim")
    monkeypatch.chdir(tmp_path)
    # its own output is replaced; with a file of another kind added, it is not
    own = tmp_path / "own"
    run_case("sim writes its own output", _sim(run, empty, own), capsys, inputs, expect_exit=0, surface="sim",
             check=lambda: (own / "front_camera" / "00000.png").is_file())
    run_case("sim --overwrite replaces its own output", _sim(run, empty, own, "--overwrite"), capsys, inputs,
             expect_exit=0, surface="sim", check=lambda: (own / "front_camera" / "00000.png").is_file())
    (own / "thesis.tex").write_text("do not delete")
    run_case("sim --overwrite of its output holding another file", _sim(run, empty, own, "--overwrite"), capsys,
             [*inputs, own], needles=("thesis.tex",), surface="sim")


# ------------------------------------------------------------------ 3. bounded work
def _path_npz(path: Path, frames: int) -> Path:
    """A camera-path npz of ``frames`` frames that compresses to almost nothing."""
    np.savez_compressed(path, seconds=np.zeros(frames), rig_to_world=np.zeros((frames, 4, 4)))
    return path


def _path_json(path: Path, seconds, translations) -> Path:
    rig = [[[1, 0, 0, t[0]], [0, 1, 0, t[1]], [0, 0, 1, t[2]], [0, 0, 0, 1]] for t in translations]
    path.write_text(json.dumps({"seconds": list(seconds), "rig_to_world": rig}))
    return path


SIM_SIZES = [
    ("--fps 1e9", [], ["--fps", "1e9"], "--fps"),
    ("--fps inf", [], ["--fps", "inf"], "--fps"),
    ("--width/--height 10^6", [], ["--width", "1000000", "--height", "1000000"], "--width"),
    ("[output] fps = 1e300", "[output]\nfps = 1e300\n", [], "field 'fps'"),
    ("[camera] fps = inf", '[camera]\npath = "interpolated"\nfps = inf\n', [], "field 'fps'"),
    ("[camera] 10^6 pixels", "[camera]\nwidth = 1000000\nheight = 1000000\n", [], "field 'width'"),
    ("[[actor]] offset 1e308", '[[actor]]\ntrack = "any"\noffset = [1e308, 0.0, 0.0]\n', [], "field 'offset'"),
    ("[[actor]] offset_world 1e6", '[[actor]]\ntrack = "any"\noffset_world = [0.0, 1e6, 0.0]\n', [],
     "field 'offset_world'"),
    ("[[insert]] trajectory 1e308", '[[insert]]\nid = "g"\nrun = "elsewhere"\ntrack = "t"\n'
                                    'trajectory = [[0.0, 1e308, 0.0], [0.1, 0.0, 0.0]]\n', [], "trajectory[1]"),
    ("lane shift 1e308", "[camera]\n[[camera.lane_shift]]\noffset = 1e308\n", [], "field 'offset'"),
    ("recorded frames over --frame-cap", "[camera]\nframes = [0, 1, 2, 3, 0, 1]\n", ["--frame-cap", "5"],
     "--frame-cap"),
]


@pytest.mark.parametrize("case", SIM_SIZES, ids=[c[0] for c in SIM_SIZES])
def test_sim_sizes_rates_and_positions_are_capped(case, setup, tmp_path, capsys):
    """Issue 41 items 3 and 7: rates, sizes, positions and frame counts over their stated caps
    (omnire/limits.py) are refused before any rendering, naming the field."""
    data, run = setup
    name, text, flags, needle = case
    scenario = _scenario(tmp_path, text or "")
    out = tmp_path / "out"
    run_case(name, _sim(run, scenario, out, *flags), capsys, [data, run, scenario], needles=(needle,),
             surface="sim", check=lambda: not out.exists())


def test_sim_width_height_zero_refused(setup, tmp_path, capsys):
    """Issue 41 item 7: --width 0 --height 0 was ignored silently."""
    data, run = setup
    out = tmp_path / "out"
    run_case("sim --width 0 --height 0", _sim(run, _scenario(tmp_path, ""), out, "--width", "0", "--height", "0"),
             capsys, [data, run], needles=("--width",), surface="sim", check=lambda: not out.exists())


def test_camera_path_files_are_bounded(setup, tmp_path, capsys):
    """Issue 41 items 3 and 4: a 10^6-frame camera path (a compressed npz of a few hundred kB),
    one over --frame-cap, one far outside the scene, and a JSON nested 150 000 levels deep."""
    data, run = setup
    cases = [
        ("10^6-frame npz path", _path_npz(tmp_path / "huge.npz", 1_000_000), [], "--frame-cap"),
        ("path over --frame-cap", _path_json(tmp_path / "long.json", np.arange(12) * 0.05, [[0, 0, 0]] * 12),
         ["--frame-cap", "10"], "--frame-cap"),
        ("path far outside the scene", _path_json(tmp_path / "far.json", [0.0, 0.1], [[1e7, 0, 0]] * 2), [],
         "extent"),
        ("path JSON nested 150000 deep", tmp_path / "deep.json", [], "nested"),
    ]
    (tmp_path / "deep.json").write_text("[" * DEEP + "]" * DEEP)
    for name, file, flags, needle in cases:
        scenario = _scenario(tmp_path, f'[camera]\npath = "file"\nfile = "{file.name}"\n', f"{file.stem}.toml")
        run_case(name, _sim(run, scenario, tmp_path / "out", *flags), capsys, [data, run, file], needles=(needle,),
                 surface="sim", check=lambda: not (tmp_path / "out").exists())


# ------------------------------------------------------------------ 4. nesting
def test_deeply_nested_documents_are_refused(setup, tmp_path, capsys):
    """Issue 41 item 4: a scenario and a batch file nested 150 000 levels deep (arrays, inline
    tables, dotted keys) are one-line errors naming the file, not RecursionErrors."""
    data, run = setup
    texts = {"array": "a = " + "[" * DEEP + "]" * DEEP + "\n",
             "inline table": "a = " + "{b = " * 20_000 + "1" + "}" * 20_000 + "\n",
             "dotted key": ".".join(["a"] * DEEP) + " = 1\n"}
    for kind, text in texts.items():
        scenario = _scenario(tmp_path, text, f"deep-{kind.replace(' ', '-')}.toml")
        run_case(f"scenario nested ({kind})", _sim(run, scenario, tmp_path / "out"), capsys, [data, run, scenario],
                 needles=(scenario.name, "nested"), surface="sim")
        run_case(f"batch file nested ({kind})", ["batch", "--config", str(scenario), "--dry-run"], capsys,
                 [data, scenario], needles=(scenario.name, "nested"), surface="batch")


# ------------------------------------------------------------------ 5. outputs that cannot be written
def test_unwritable_outputs_are_one_line_errors(setup, tmp_path, capsys):
    """Issue 41 item 5: a file where a directory is expected (sim, export, render, batch), and
    a directory where an export file goes: one line naming the path, nothing partial left."""
    data, run = setup
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    inputs = [data, run, blocker]
    empty = _scenario(tmp_path, "")
    run_case("sim output under a file", _sim(run, empty, blocker / "out"), capsys, inputs, needles=("blocker",),
             surface="sim")
    run_case("export output under a file", ["export", str(run), "--output", str(blocker / "scene.ply")], capsys,
             inputs, needles=("blocker",), surface="export")
    run_case("export --per-node output under a file",
             ["export", str(run), "--per-node", "--output", str(blocker / "parts")], capsys, inputs,
             needles=("blocker",), surface="export")
    run_case("render output under a file", ["render", str(run), "--frames", "0", "--output", str(blocker / "r")],
             capsys, inputs, needles=("blocker",), surface="render")
    run_case("batch output under a file",
             ["batch", "--scenes", f"s=pandaset:{data}", "--methods", "3dgs", "--output", str(blocker / "b")],
             capsys, inputs, needles=("blocker",), surface="batch")
    seq = tmp_path / "seq"
    (seq / "scene_0001.ply").mkdir(parents=True)  # where the second file of the sequence goes
    run_case("export sequence with a folder in the way",
             ["export", str(run), "--frames", "0,1", "--output", str(seq / "scene.ply"), "--overwrite"], capsys,
             inputs, needles=("scene_0001.ply",), surface="export",
             check=lambda: sorted(p.name for p in seq.iterdir()) == ["scene_0001.ply"])


def test_full_and_read_only_filesystems(setup, tmp_path, capsys):
    """Issue 41 item 5: a real disk-full and read-only file system (a tiny tmpfs): one-line
    errors naming the path, and nothing left on it."""
    data, run = setup
    empty = _scenario(tmp_path, "")
    with _tiny_filesystem(tmp_path / "small") as small:
        for name, argv, surface in [
            ("sim onto a full disk", ["sim", str(run), "--scenario", str(empty), "--output", str(small / "sim"),
                                      "--no-progress", "--no-video"], "sim"),
            ("export onto a full disk", ["export", str(run), "--output", str(small / "scene.ply")], "export"),
            ("render onto a full disk", ["render", str(run), "--split", "all", "--depth", "--output",
                                         str(small / "r")], "render"),
        ]:
            run_case(name, argv, capsys, [data, run], needles=(str(small),), surface=surface,
                     check=lambda: [p for p in small.rglob("*") if p.is_file()] == [])
        subprocess.run(["mount", "-o", "remount,ro", str(small)], check=True)
        for name, argv, surface in [
            ("sim onto a read-only file system", _sim(run, empty, small / "sim"), "sim"),
            ("export onto a read-only file system", ["export", str(run), "--output", str(small / "scene.ply")],
             "export"),
            ("batch onto a read-only file system",
             ["batch", "--scenes", f"s=pandaset:{data}", "--methods", "3dgs", "--output", str(small / "b")], "batch"),
        ]:
            run_case(name, argv, capsys, [data, run], needles=(str(small),), surface=surface)


# ------------------------------------------------------------------ 6. malformed numbers
BATCH_BAD = [
    ("num_cpus = nan", "num_cpus = nan\n", [], "num_cpus"),
    ("seconds = nan", "seconds = nan\n", [], "seconds"),
    ("[[method]] num_cpus = nan", '[[method]]\nname = "3dgs"\nnum_cpus = nan\n', [], "num_cpus"),
    ("--num-cpus nan", "", ["--num-cpus", "nan"], "--num-cpus"),
    ("--seconds nan", "", ["--seconds", "nan"], "--seconds"),
    ("--local-cpus -1", "", ["--local-cpus", "-1"], "--local-cpus"),
]


@pytest.mark.parametrize("case", BATCH_BAD, ids=[c[0] for c in BATCH_BAD])
def test_batch_bad_numbers(case, setup, tmp_path, capsys):
    """Issue 41 item 6: nan resources and budgets, negative local CPUs (file and flags)."""
    data, _ = setup
    name, text, flags, needle = case
    config = _scenario(tmp_path, text + f'[[scene]]\nname = "s"\ndataparser = "pandaset"\ndata = "{data}"\n'
                       + ('[[method]]\nname = "3dgs"\n' if "[[method]]" not in text else ""), "batch.toml")
    argv = ["batch", "--config", str(config), *flags, "--output",
            str(tmp_path / "b"), "--dry-run"]
    run_case(name, argv, capsys, [data, config], needles=(needle,), surface="batch")


def test_batch_config_not_utf8(setup, tmp_path, capsys):
    data, _ = setup
    config = tmp_path / "latin1.toml"
    config.write_bytes('method_args = "--caf\xe9"\n'.encode("latin-1"))
    run_case("batch config not UTF-8", ["batch", "--config", str(config), "--dry-run"], capsys, [config],
             needles=("latin1.toml", "UTF-8"), surface="batch")


def test_motion_npz_with_bad_fps(tmp_path):
    """Issue 41 items 3 and 6: a body-pose sequence whose fps is an array, a string or over the
    cap, or of a million frames (compressed to a few kB): one line naming the file, nothing
    decompressed (read through the sim's loader; the demo run has no body model)."""
    from omnire.errors import UserError
    from omnire_sim.edits import Motion, Where
    from omnire_sim.engine import load_body_sequence

    for name, fps, frames in [("non-scalar fps", np.array([30.0, 60.0]), 4), ("non-numeric fps", np.array("fast"), 4),
                              ("fps 1e9", np.array(1e9), 4), ("fps nan", np.array(np.nan), 4),
                              ("10^6 frames in a small file", np.array(30.0), 1_000_000)]:
        path = tmp_path / f"{name.replace(' ', '-')}.npz"
        np.savez_compressed(path, body_pose=np.zeros((frames, 69), dtype=np.float32), fps=fps)
        traceback, code, text = None, 0, ""
        try:
            load_body_sequence(path, Motion("sequence", file=path), Where("scenario.toml", "[[actor]] #1", 3))
        except UserError as exc:
            code, text = 2, str(exc)
        except Exception as exc:  # noqa: BLE001 - what the case looks for
            traceback, code = repr(exc), -1
        wrong = code != 2 or path.name not in text or "\n" in text
        record("sim", f"motion npz {name}", exit=code, traceback=traceback, wrong=wrong)
        assert traceback is None, f"{name}: {traceback}"
        assert not wrong, f"{name}: {text!r}"


# ------------------------------------------------------------------ 7. export frames
EXPORT_FRAMES = [("1,1", "more than once"), ("0:1000000", "0 <= start < stop"), ("-1,2", "0.."),
                 ("2:1", "0 <= start < stop"), ("0:4:0", "step")]


@pytest.mark.parametrize("case", EXPORT_FRAMES, ids=[c[0] for c in EXPORT_FRAMES])
def test_export_frames_one_rule(case, setup, tmp_path, capsys):
    """Issue 41 item 7: repeated frames and out-of-range bounds are refused alike, naming the
    scene's frame range (before: '1,1' reported two files and wrote one; '0:1000000' was
    clipped silently)."""
    data, run = setup
    spec, needle = case
    out = tmp_path / "scene.ply"
    run_case(f"export --frames {spec}", ["export", str(run), "--frames", spec, "--output", str(out)], capsys,
             [data, run], needles=("--frames", needle), surface="export", check=lambda: not any(tmp_path.iterdir()))
