"""Hostile inputs: corrupt files, malicious pickles, tampered run directories, broken plugins
and bad flags, each through the real CLI entry point (in process, so a traceback surfaces as
an exception). Every case must end with a non-zero exit and a one-line message naming the
culprit (or, where a fallback is documented, succeed with the right result), and must leave
its input files unchanged. The count is printed at the end of the test session."""
from __future__ import annotations

import gzip
import json
import os
import pickle
import shutil
from pathlib import Path

import pytest

from omnire.cli import main

from hostile import record, run_case
from scene_helpers import DEMO_SCENE

pytestmark = pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
SMALL = ["--end-frame", "4", "--holdout-every", "2", "--scale", "0.25", "--method.rasterizer", "torch",
         "--method.nodes.background.max-lidar-points", "2000", "--method.nodes.background.num-far-points", "200",
         "--trainer.no-progress", "--trainer.eval-train-views", "2"]
class _Evil:
    def __reduce__(self):
        return (os.system, ("touch /tmp/omnire-pwned",))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny run of 3dgs on the demo cut with checkpoints at steps 2 and 4."""
    root = tmp_path_factory.mktemp("runs")
    code = main(["train", "3dgs", "pandaset", "--data", str(DEMO_SCENE), *SMALL, "--trainer.max-steps", "4",
                 "--trainer.checkpoint-every", "2", "--trainer.output-dir", str(root), "--trainer.run-name", "base"])
    assert code == 0
    return root / "base"


def _copy_run(trained: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(trained, dst)
    return dst


def _copy_scene(tmp_path: Path) -> Path:
    dst = tmp_path / "scene"
    shutil.copytree(DEMO_SCENE, dst)
    return dst


# ---------------------------------------------------------------------------------- corrupt data
def _truncate_image(scene: Path) -> str:
    img = scene / "camera" / "front_camera" / "01.jpg"
    img.write_bytes(img.read_bytes()[: img.stat().st_size // 3])
    return "01.jpg"


def _zero_focal(scene: Path) -> str:
    path = scene / "camera" / "front_camera" / "intrinsics.json"
    data = json.loads(path.read_text())
    data["fx"] = 0.0
    path.write_text(json.dumps(data))
    return "focal lengths"


def _far_principal_point(scene: Path) -> str:
    path = scene / "camera" / "front_camera" / "intrinsics.json"
    data = json.loads(path.read_text())
    data["cx"] = 1e6
    path.write_text(json.dumps(data))
    return "principal point"


def _nan_timestamp(scene: Path) -> str:
    path = scene / "lidar" / "timestamps.json"
    stamps = json.loads(path.read_text())
    stamps[1] = float("nan")
    path.write_text(json.dumps(stamps))
    return "timestamps"


def _evil_lidar_pickle(scene: Path) -> str:
    (scene / "lidar" / "00.pkl.gz").write_bytes(gzip.compress(pickle.dumps(_Evil())))
    return "refused as unsafe"


def _lidar_bomb(scene: Path) -> str:
    (scene / "lidar" / "00.pkl.gz").write_bytes(gzip.compress(b"\0" * (300 * 2**20), compresslevel=9))
    return "expands to more than"


def _empty_cuboids(scene: Path) -> str:
    (scene / "annotations" / "cuboids" / "02.pkl.gz").write_bytes(b"")
    return "02.pkl.gz"


def _edit_lidar_column(scene: Path, column: str, value: float) -> None:
    from omnire_pandaset.dataparser import load_frame_table
    import numpy as np
    import pandas as pd

    path = scene / "lidar" / "00.pkl.gz"
    df = load_frame_table(path)
    df.index = pd.Index(np.arange(len(df)), dtype=np.int64)  # a RangeIndex pickles as a global the reader refuses
    df.loc[7, column] = value
    path.write_bytes(gzip.compress(pickle.dumps(df)))


def _lidar_intensity_out_of_range(scene: Path) -> str:
    _edit_lidar_column(scene, "i", -3.0)
    return "00.pkl.gz: column i (intensity) must hold numbers in 0..255"


def _lidar_time_nan(scene: Path) -> str:
    _edit_lidar_column(scene, "t", float("nan"))
    return "00.pkl.gz: column t (per-point time) holds NaN or inf"


CORRUPT = {"lidar intensity out of range": _lidar_intensity_out_of_range, "lidar time nan": _lidar_time_nan,
           "truncated jpeg": _truncate_image, "zero focal length": _zero_focal,
           "principal point outside": _far_principal_point, "nan timestamp": _nan_timestamp,
           "malicious lidar pickle": _evil_lidar_pickle, "gzip bomb": _lidar_bomb,
           "empty cuboid file": _empty_cuboids}


@pytest.mark.parametrize("case", sorted(CORRUPT))
def test_corrupt_dataset(case, tmp_path, capsys):
    scene = _copy_scene(tmp_path)
    needle = CORRUPT[case](scene)
    run_case(case, ["train", "3dgs", "pandaset", "--data", str(scene), *SMALL, "--trainer.max-steps", "2",
                    "--trainer.output-dir", str(tmp_path / "out")], capsys, [scene], needles=(needle,))
    assert not Path("/tmp/omnire-pwned").exists()


# ---------------------------------------------------------------------------------- run directories
def _malformed_json(run: Path) -> tuple[str, int]:
    (run / "run.json").write_text("{not json")
    return "run.json", 2


def _missing_field(run: Path) -> tuple[str, int]:
    info = json.loads((run / "run.json").read_text())
    del info["argv"]
    (run / "run.json").write_text(json.dumps(info))
    return "'argv' is missing", 2


def _argv_wrong_type(run: Path) -> tuple[str, int]:
    info = json.loads((run / "run.json").read_text())
    info["argv"] = "train 3dgs"
    (run / "run.json").write_text(json.dumps(info))
    return "'argv' must be a list", 2


def _no_checkpoints(run: Path) -> tuple[str, int]:
    shutil.rmtree(run / "checkpoints")
    return "no checkpoints", 2


def _only_checkpoint_truncated(run: Path) -> tuple[str, int]:
    (run / "checkpoints" / "step-000002.pt").unlink()
    ckpt = run / "checkpoints" / "step-000004.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:1000])
    return "step-000004.pt", 2


def _malicious_checkpoint(run: Path) -> tuple[str, int]:
    for p in (run / "checkpoints").glob("*.pt"):
        p.unlink()
    import torch

    torch.save({"step": 4, "model": _Evil()}, run / "checkpoints" / "step-000004.pt")
    return "refused as unsafe", 2


def _newest_empty(run: Path) -> tuple[str, int]:
    (run / "checkpoints" / "step-000004.pt").write_bytes(b"")
    return "step 2", 0  # falls back to the intact step-2 checkpoint


TAMPERED = {"malformed run.json": _malformed_json, "run.json without argv": _missing_field,
            "run.json argv not a list": _argv_wrong_type, "no checkpoints": _no_checkpoints,
            "truncated only checkpoint": _only_checkpoint_truncated, "malicious checkpoint": _malicious_checkpoint,
            "empty newest checkpoint": _newest_empty}


@pytest.mark.parametrize("case", sorted(TAMPERED))
def test_tampered_run_directory(case, trained, tmp_path, capsys):
    run = _copy_run(trained, tmp_path)
    needle, expect = TAMPERED[case](run)
    run_case(case, ["eval", str(run)], capsys, [run], expect_exit=expect, needles=(needle,))
    assert not Path("/tmp/omnire-pwned").exists()


def test_not_a_run_directory(tmp_path, capsys):
    run_case("eval of a plain folder", ["eval", str(tmp_path)], capsys, [tmp_path], needles=("not a run directory",))
    run_case("eval of a missing path", ["eval", str(tmp_path / "nope")], capsys, [tmp_path],
             needles=("not a run directory",))


# ---------------------------------------------------------------------------------- bad flags
BAD_FLAGS = {
    "zero steps": (["--trainer.max-steps", "0"], "--trainer.max-steps"),
    "negative steps": (["--trainer.max-steps", "-5"], "--trainer.max-steps"),
    "zero log interval": (["--trainer.log-every", "0"], "--trainer.log-every"),
    "zero checkpoint interval": (["--trainer.checkpoint-every", "0"], "--trainer.checkpoint-every"),
    "negative seconds": (["--trainer.max-seconds", "-1"], "--trainer.max-seconds"),
    "infinite seconds": (["--trainer.max-seconds", "inf"], "--trainer.max-seconds inf: must be a finite number"),
    "negative threads": (["--trainer.threads", "-2"], "--trainer.threads"),
    "cuda on a cpu build": (["--trainer.device", "cuda"], "--trainer.device"),
    "unknown device": (["--trainer.device", "banana"], "--trainer.device"),
    "run name with a slash": (["--trainer.run-name", "a/b"], "--trainer.run-name"),
    "unknown camera": (["--cameras", "roof_camera"], "roof_camera"),
    "frames outside the log": (["--start-frame", "30", "--end-frame", "90"], "outside the log"),
    "bad ego-mask choice": (["--ego-masks", "/no/such/folder"], "--ego-masks"),
    "unknown observer": (["--trainer.observers", "nothing-such"], "nothing-such"),
}


@pytest.mark.parametrize("case", sorted(BAD_FLAGS))
def test_bad_flags(case, tmp_path, capsys):
    import torch

    flags, needle = BAD_FLAGS[case]
    if case == "cuda on a cpu build" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    run_case(case, ["train", "3dgs", "pandaset", "--data", str(DEMO_SCENE), *SMALL, "--trainer.max-steps", "2",
                    "--trainer.output-dir", str(tmp_path / "out"), *flags], capsys, [DEMO_SCENE], needles=(needle,),
             check=lambda: not any((tmp_path / "out").glob("*/checkpoints")))


def test_run_directory_reuse_and_resume_mismatch(trained, tmp_path, capsys):
    run = _copy_run(trained, tmp_path)
    base = ["train", "3dgs", "pandaset", "--data", str(DEMO_SCENE), *SMALL, "--trainer.max-steps", "6"]
    run_case("reused run name", base + ["--trainer.output-dir", str(tmp_path), "--trainer.run-name", "run"],
             capsys, [run], needles=("already holds a run",))
    changed = [a if a != "4" else "3" for a in base]  # --end-frame 4 -> 3
    run_case("resume with another frame range", changed + ["--trainer.resume", str(run)], capsys, [run],
             needles=("data selection",))
    run_case("resume with another method", ["train", "streetgs", *base[2:], "--trainer.resume", str(run)], capsys,
             [run], needles=("trained 3dgs",))


# ---------------------------------------------------------------------------------- broken plugins
def _module(name: str, source: str):
    import textwrap
    import types

    module = types.ModuleType(name)
    exec(textwrap.dedent(source), module.__dict__)  # noqa: S102 - test plugins written here
    return module


IMPOSTOR = """
from omnire.api import NodeTypeSpec, MethodSpec, MethodConfig, hookimpl
from omnire.nodes.background import BackgroundConfig

@hookimpl
def omnire_register_node_types(registry):
    registry.register(NodeTypeSpec("rigid", "an impostor", BackgroundConfig, categories=frozenset({"vehicle"})))

@hookimpl
def omnire_register_methods(registry):
    registry.register(MethodSpec("impostor-method", "uses the impostor", MethodConfig))
"""

HALF_WAY = """
from omnire.api import LossSpec, hookimpl

@hookimpl
def omnire_register_losses(registry):
    registry.register(LossSpec("half_way_loss", "registered before the failure", lambda ctx: None))
    raise RuntimeError("fails half way")
"""

BROKEN_CALLS = """
from omnire.api import MethodSpec, RasterizerSpec, hookimpl

def _factory():
    raise RuntimeError("method factory broken on purpose")

def _available(device):
    raise RuntimeError("available() broken on purpose")

@hookimpl
def omnire_register_methods(registry):
    registry.register(MethodSpec("broken-method", "its factory raises", _factory))

@hookimpl
def omnire_register_rasterizers(registry):
    registry.register(RasterizerSpec("broken-raster", "its available() raises", lambda **kw: None, _available, 999))
"""


def _record(case: str, ok: bool, detail: str = "") -> None:
    record("plugins", case, exit=0 if ok else 1, wrong=not ok)
    assert ok, f"{case}: {detail}"


def test_plugin_takeover_is_refused_in_any_order():
    from omnire.plugins import load_plugins

    for order in ("impostor", "impostor-z"):  # module names sort before and after the real plugins
        plugins = load_plugins(extra_modules=(_module(order, IMPOSTOR),))
        refused = [f for f in plugins.failures if f.stage == "conflict"]
        _record(f"node type takeover ({order})", "rigid" not in plugins.node_types
                and "impostor-method" not in plugins.methods and "streetgs" not in plugins.methods
                and any("rigid" in f.error and "all of them refused" in f.error for f in refused)
                and "omnire" not in plugins.methods or "rigid" not in plugins.node_types,
                str([f.describe() for f in plugins.failures]))
    plugins = load_plugins(extra_modules=(_module("takes-builtin", IMPOSTOR.replace('"rigid"', '"background"')),))
    _record("built-in name takeover", plugins.node_types.provenance("background").distribution == "omnire"
            and any("which the core provides" in f.error for f in plugins.failures))


def test_plugin_failing_half_way_leaves_nothing():
    from omnire.plugins import load_plugins

    plugins = load_plugins(extra_modules=(_module("half-way", HALF_WAY),))
    _record("partial registration", "half_way_loss" not in plugins.losses
            and any("fails half way" in f.error for f in plugins.failures))


def test_broken_components_do_not_stop_runs_that_do_not_use_them():
    from omnire.plugins import load_plugins
    from omnire.rasterization import select_rasterizer
    from omnire.runconfig import parse_train_args

    plugins = load_plugins(extra_modules=(_module("broken-calls", BROKEN_CALLS),))
    config = parse_train_args(["3dgs", "pandaset", "--data", str(DEMO_SCENE)], plugins)
    _record("method factory raises", config.method_name == "3dgs"
            and any("method factory broken" in f.error for f in plugins.failures))
    rasterizer = select_rasterizer(plugins, "auto", "cpu")
    _record("rasterizer available() raises", rasterizer.name != "broken-raster"
            and any("available() broken" in f.error for f in plugins.failures))
