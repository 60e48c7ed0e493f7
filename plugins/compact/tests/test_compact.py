"""omnire compact through the real CLI on a tiny trained run: the compacted run holds about
the kept fraction of each node's Gaussians, records where it came from, and eval, render,
export and the scene runtime read it; bad input is a one-line error."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

from plyfile import PlyData

from hostile import run_case

OMNIRE = str(Path(sys.executable).parent / "omnire")


def omnire(*argv: str) -> str:
    proc = subprocess.run([OMNIRE, *argv], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (f"omnire {' '.join(argv)}: exit {proc.returncode}\n"
                                  f"{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    return proc.stdout


def test_compacted_run_is_read_by_every_tool(tiny_run, tmp_path):
    out = tmp_path / "compacted"
    text = omnire("compact", str(tiny_run), "--output", str(out), "--keep-fraction", "0.5", "--finetune-steps", "1",
                  "--eval-train-views", "1", "--threads", "1", "--no-progress")
    assert "compacted" in text and "Gaussians" in text
    assert not list(tmp_path.glob(".*partial*"))
    report = json.loads((out / "compact.json").read_text())
    for node, c in report["counts"].items():
        assert c["before"] > 0 and c["after"] <= math.ceil(0.5 * c["before"]) + 50, node  # ceil per actor instance
        assert c["after"] >= 0.5 * c["before"], node
    before = sum(c["before"] for c in report["counts"].values())
    states = report["states"]
    assert states["source"]["num_gaussians"] == before
    assert states["compacted"]["num_gaussians"] <= 0.51 * before
    assert states["compacted"]["checkpoint_bytes"] < states["source"]["checkpoint_bytes"]
    assert states["compacted"]["step"] == states["source"]["step"] + 1
    info = json.loads((out / "run.json").read_text())
    assert info["compacted_from"]["source_run"] == str(tiny_run.resolve())
    assert info["compacted_from"]["keep_fraction"] == 0.5

    from omnire.plugins import load_plugins
    from omnire.runtime import Reconstruction

    recon = Reconstruction.from_run(out, load_plugins(), read_only=True)
    assert recon.num_gaussians() == states["compacted"]["num_gaussians"]
    omnire("eval", str(out), "--train-views", "1")
    omnire("render", str(out), "--split", "train", "--frames", "0", "--output", str(tmp_path / "renders"))
    assert len(list((tmp_path / "renders").glob("*.png"))) == len(recon.scene.cameras)
    omnire("export", str(out), "--output", str(tmp_path / "scene.ply"))
    count = PlyData.read(str(tmp_path / "scene.ply"))["vertex"].count
    assert 0 < count <= recon.num_gaussians()


def test_bad_input_is_one_line(tmp_path, capsys):
    plain = tmp_path / "plain"
    plain.mkdir()
    run_case("keep fraction above 1", ["compact", str(plain), "--output", str(tmp_path / "a"), "--keep-fraction",
                                       "1.5"], capsys, [plain], needles=("--keep-fraction 1.5",))
    run_case("negative fine-tune", ["compact", str(plain), "--output", str(tmp_path / "a"), "--finetune-steps", "-1"],
             capsys, [plain], needles=("--finetune-steps -1",))
    run_case("output exists", ["compact", str(plain), "--output", str(plain)], capsys, [plain],
             needles=("exists",))
    run_case("not a run", ["compact", str(plain), "--output", str(tmp_path / "a")], capsys, [plain],
             needles=("run.json",), check=lambda: not (tmp_path / "a").exists())
    run_case("no such run", ["compact", str(tmp_path / "missing"), "--output", str(tmp_path / "a")], capsys, [],
             needles=("no such run directory",))


def test_keeping_everything_without_finetuning_copies_the_model(tiny_run, tmp_path):
    import torch

    from omnire.api import RunDirectory
    from omnire.cli import main

    out = tmp_path / "copy"
    assert main(["compact", str(tiny_run), "--output", str(out), "--keep-fraction", "1", "--finetune-steps", "0",
                 "--eval-train-views", "1", "--threads", "1", "--no-progress"]) in (0, None)
    _, source = RunDirectory(tiny_run).load_latest_checkpoint()
    path, copy = RunDirectory(out).load_latest_checkpoint()
    assert copy["step"] == source["step"] and (out / "eval" / f"step-{copy['step']:06d}.json").is_file()
    assert set(copy["model"]) == set(source["model"])
    for key, value in source["model"].items():
        if torch.is_tensor(value):
            assert torch.equal(copy["model"][key], value), key
    report = json.loads((out / "compact.json").read_text())
    assert list(report["states"]) == ["source", "compacted"]
    assert all(c["before"] == c["after"] for c in report["counts"].values())


def test_finetuning_lowers_the_training_loss(tiny_run, tmp_path):
    """Fine-tuning after pruning trains the kept Gaussians on the training views: the
    training-view PSNR (every training view) rises from the pruned state, and the checkpoint
    and run.json agree on the new step. The source's run.json records its --data relative to
    the directory it was trained in (as ``omnire train`` does for a relative path), which the
    branch must match to the absolute path of the recorded command line."""
    import shutil

    source = tmp_path / "runs" / "omnire"
    shutil.copytree(tiny_run, source)
    info = json.loads((source / "run.json").read_text())
    data = Path(info["settings"]["dataparser"]["data"])
    info["cwd"], info["settings"]["dataparser"]["data"] = str(data.parent), data.name
    (source / "run.json").write_text(json.dumps(info))
    out = tmp_path / "tuned"
    omnire("compact", str(source), "--output", str(out), "--keep-fraction", "0.3", "--finetune-steps", "12",
           "--eval-train-views", "0", "--threads", "1", "--no-progress")
    states = json.loads((out / "compact.json").read_text())["states"]
    assert list(states) == ["source", "pruned", "compacted"]
    assert states["compacted"]["train_psnr"] > states["pruned"]["train_psnr"] + 0.1, states
    assert states["compacted"]["num_gaussians"] <= states["pruned"]["num_gaussians"]
    step = states["source"]["step"] + 12
    assert states["compacted"]["step"] == step
    recorded = json.loads((out / "run.json").read_text())
    argv = recorded["argv"]
    assert argv[argv.index("--trainer.max-steps") + 1] == str(step)
    assert recorded["schedule"]["max_steps"] == step and recorded["schedule"]["steps"] == step
    assert [p.name for p in (out / "checkpoints").glob("step-*.pt")] == [f"step-{step:06d}.pt"]
