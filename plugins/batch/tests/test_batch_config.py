"""Batch definitions (TOML and flags) -> jobs, with errors that name the file, line and field;
run-directory reading across resumed attempts. No Ray here."""
import json
from pathlib import Path

import pytest

from omnire.api import ConfigError
from omnire.plugins import load_plugins
from omnire_batch.jobs import BENCHMARKS, BatchArgs, args_with_toml, build_jobs, config_path_in, load_toml
from omnire.rundir import RunDirectory
from omnire_batch.runs import run_state

GOOD = """\
steps = 300
seeds = [0, 3]
method_args = "--method.rasterizer cpu"
num_cpus = 1
memory_gb = 2

[[scene]]
name = "demo"
dataparser = "pandaset"
data = "data/demo/pandaset_002"
args = "--scale 0.25 --end-frame 20"

[[scene]]
name = "urban"
synth = "urban"
synth_args = "--frames 12"

[[method]]
name = "3dgs"

[[method]]
name = "omnire"
memory_gb = 6

[[variant]]
name = "base"

[[variant]]
name = "dim"
args = "--method.nodes.background.init-opacity 0.05"
"""


@pytest.fixture(scope="module")
def plugins():
    return load_plugins()


def jobs_from(tmp_path: Path, text: str, argv=(), plugins=None):
    path = tmp_path / "batch.toml"
    path.write_text(text)
    data, src = load_toml(path)
    import tyro

    args = tyro.cli(BatchArgs, args=["--config", str(path), *argv], default=args_with_toml(BatchArgs(), data, src))
    return build_jobs(args, data, src, plugins)


def test_toml_gives_scenes_x_methods_x_variants_x_seeds(tmp_path, monkeypatch, plugins):
    monkeypatch.chdir(tmp_path)
    jobs = jobs_from(tmp_path, GOOD, ["--steps", "200"], plugins)
    assert len(jobs) == 2 * 2 * 2 * 2
    assert [j.key for j in jobs[:4]] == ["demo/3dgs+base-seed0", "demo/3dgs+base-seed3", "demo/3dgs+dim-seed0",
                                        "demo/3dgs+dim-seed3"]
    dim = jobs[2]
    args = dim.train_args()
    assert args[:6] == ["train", "3dgs", "pandaset", "--data", str(tmp_path / "data/demo/pandaset_002"), "--scale"]
    assert args[args.index("--trainer.max-steps") + 1] == "200"  # the flag overrides the file
    assert args[args.index("--trainer.eval-every") + 1] == "50"  # 4 evaluations along the way
    assert args[args.index("--trainer.seed") + 1] == "0"
    assert "--method.nodes.background.init-opacity" in args and "--method.rasterizer" in args
    assert dim.run_dir == tmp_path / "outputs/batch/runs/demo/3dgs+dim-seed0"
    assert "--trainer.threads" not in dim.identity() and dim.identity()[1:3] == ["3dgs", "pandaset"]
    urban = [j for j in jobs if j.scene.name == "urban"][0]
    assert urban.scene.dataparser == "processed" and urban.scene.synth == "urban"
    assert urban.scene.data == tmp_path / "outputs/batch/scenes/urban" and urban.scene.synth_args == ("--frames", "12")
    assert {j.memory_gb for j in jobs if j.method.label == "omnire"} == {6.0}
    assert {j.memory_gb for j in jobs if j.method.label == "3dgs"} == {2.0}


def test_flags_alone_define_a_batch(tmp_path):
    import tyro

    args = tyro.cli(BatchArgs, args=["--scenes", "a=synth:crowd --frames 10", "b=pandaset:/x/y --scale 0.5",
                                     "--methods", "3dgs", "lo=3dgs --method.x 1", "--seeds", "1", "2",
                                     "--num-gpus", "1", "--output", str(tmp_path)])
    jobs = build_jobs(args)
    assert len(jobs) == 2 * 2 * 2
    assert jobs[0].scene.synth == "crowd" and jobs[0].scene.synth_args == ("--frames", "10")
    assert jobs[-1].key == "b/lo-seed2" and jobs[-1].flags == ["--method.x", "1"]
    assert jobs[-1].train_args()[-2:] == ["--trainer.device", "cuda"]  # asked for a GPU


@pytest.mark.parametrize("text, expected", [
    ('steps = 10\nstepz = 3\n', r"batch.toml:2: top level, field 'stepz': unknown key"),
    ('steps = "ten"\n', r"batch.toml:1: top level, field 'steps': expected an integer, got 'ten'"),
    ('seeds = [0, "1"]\n', r"batch.toml:1: top level, field 'seeds': expected a list of integers"),
    ('[[scene]]\nname = "a"\ndata = "x"\n', r"batch.toml:1: \[\[scene\]\] #1: missing field 'dataparser'"),
    ('[[scene]]\nname = "a"\ndataparser = "pandaset"\ndata = "x"\n\n[[scene]]\nname = "b c"\n',
     r"batch.toml:7: \[\[scene\]\] #2, field 'name': expected a name of letters"),
    ('[[method]]\nname = "3dgs"\nargs = "--x"\nnum_cpu = 2\n', r"batch.toml:4: \[\[method\]\] #1, field 'num_cpu': unknown key"),
    ('[[methods]]\nname = "3dgs"\n', r"field 'methods': unknown key .* did you mean \[\[method\]\]"),
    ('steps = 1\nseeds = = 2\n', r"batch.toml: not valid TOML: .*line 2"),
    # a multi-line string holding a table header and a '#' in a string do not move the lines
    # (the core TOML reader, omnire/io/documents.py)
    ('method_args = """--x\n[[method]]\n"""\nsteps = 2 # "\n[[method]]\nname = "a"\nargs = "--x #1"\nnum_cpus = -1\n',
     r"batch.toml:8: \[\[method\]\] #1, field 'num_cpus': expected a positive number"),
    ('num_cpus = nan\n', r"batch.toml:1: top level, field 'num_cpus': expected a finite number, got nan"),
    ('a = ' + '[' * 1000 + ']' * 1000 + '\n', r"batch.toml line 1: nested more than 64 levels deep"),
])
def test_toml_errors_name_the_line_and_field(tmp_path, text, expected):
    with pytest.raises(ConfigError, match=expected):
        jobs_from(tmp_path, text + '\n[[method]]\nname = "3dgs"\n' if "[[method" not in text else text)


def test_semantic_errors(tmp_path, plugins):
    base = '[[scene]]\nname = "a"\ndataparser = "pandaset"\ndata = "x"\n'
    with pytest.raises(ConfigError, match=r"batch.toml:8: \[\[method\]\] #1, field 'method': unknown method 'nope'"):
        jobs_from(tmp_path, base + '\n[[method]]\nname = "x"\nmethod = "nope"\n', plugins=plugins)
    with pytest.raises(ConfigError, match=r"batch.toml:3: \[\[scene\]\] #1, field 'dataparser': unknown dataparser 'pandaseT'"):
        jobs_from(tmp_path, base.replace('"pandaset"', '"pandaseT"') + '[[method]]\nname = "3dgs"\n', plugins=plugins)
    with pytest.raises(ConfigError, match="method label names must be unique, repeated: 3dgs"):
        jobs_from(tmp_path, base + '[[method]]\nname = "3dgs"\n[[method]]\nname = "3dgs"\n')
    with pytest.raises(ConfigError, match="no scene"):
        jobs_from(tmp_path, '[[method]]\nname = "3dgs"\n')
    with pytest.raises(ConfigError, match=r"--seeds: expected distinct non-negative integers, got \[1, 1\]"):
        jobs_from(tmp_path, base + '[[method]]\nname = "3dgs"\n', ["--seeds", "1", "1"])
    with pytest.raises(ConfigError, match=r"batch.toml:1: top level, field 'checkpoints': expected at least 1"):
        jobs_from(tmp_path, "checkpoints = 0\n" + base + '[[method]]\nname = "3dgs"\n')
    import tyro

    for bad, msg in [("a=pandaset", "expected \"NAME=DATAPARSER:PATH"), ("a b=pandaset:x", "NAME: expected a name")]:
        with pytest.raises(ConfigError, match=msg):
            build_jobs(tyro.cli(BatchArgs, args=["--scenes", bad, "--methods", "3dgs"]))
    with pytest.raises(ConfigError, match="not both"):
        config_path_in(["--config", "a.toml", "--benchmark", "multiscene"])
    with pytest.raises(ConfigError, match="no such benchmark .*multiscene"):
        config_path_in(["--benchmark=nope"])


def test_shipped_benchmark_is_valid(plugins, monkeypatch, tmp_path):
    monkeypatch.chdir(Path(__file__).resolve().parents[3])  # its data paths are relative to the repo
    path = config_path_in(["--benchmark", "multiscene"])
    assert path == BENCHMARKS / "multiscene.toml"
    data, src = load_toml(path)
    jobs = build_jobs(args_with_toml(BatchArgs(), data, src), data, src, plugins)
    scenes = {j.scene.name for j in jobs}
    assert {"pandaset-002-40-59", "pandaset-002-60-79", "synth-urban", "synth-highway", "synth-crowd"} <= scenes


def _write_metrics(run: Path, records: list[dict]) -> None:
    run.mkdir(parents=True, exist_ok=True)
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_metrics_of_a_resumed_run_read_as_one_run(tmp_path):
    ev = {"novel_view": {"full_psnr": 20.0, "copy_full_psnr": 18.0}, "num_gaussians": 10}
    first = [{"step": s, "wall": s / 10, "its": 10.0} for s in (25, 50, 75, 100, 125)]
    first.insert(4, {"step": 100, "wall": 10.0, "eval": ev})
    # interrupted after step 125, resumed from the checkpoint at step 100: the trainer appended,
    # its clock restarted at zero, and a cut line was left behind
    second = [{"step": s, "wall": (s - 100) / 10, "its": 10.0} for s in (125, 150, 175, 200)]
    final = {"step": 200, "wall": 10.0, "eval": dict(ev, num_gaussians=12), "final": True}
    run = tmp_path / "run"
    _write_metrics(run, first + second + [final])
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"step": 2')
    recs = RunDirectory(run).read_metrics()
    steps = [r["step"] for r in recs]
    assert steps == [25, 50, 75, 100, 100, 125, 150, 175, 200, 200]
    assert [r["wall"] for r in recs if "its" in r] == [2.5, 5.0, 7.5, 10.0, 12.5, 15.0, 17.5, 20.0]
    res = RunDirectory(run).results()
    assert res["steps_done"] == 200 and res["final"]["train_seconds"] == 20.0
    assert [c["step"] for c in res["curve"]] == [100, 200] and res["train_its"] == 10.0
    assert res["final"]["novel_view.copy_full_psnr"] == 18.0 and res["final"]["num_gaussians"] == 12
    # a trainer that truncates on resume and keeps its clock: nothing to fix
    _write_metrics(run, first[:5] + [{"step": s, "wall": s / 10, "its": 10.0} for s in (125, 150)])
    assert [r["wall"] for r in RunDirectory(run).read_metrics() if "its" in r] == [2.5, 5.0, 7.5, 10.0, 12.5, 15.0]


def test_run_state(tmp_path):
    import tyro

    job = build_jobs(tyro.cli(BatchArgs, args=["--scenes", "a=pandaset:/x", "--methods", "3dgs",
                                               "--output", str(tmp_path)]))[0]
    assert run_state(job.run_dir, job.identity()) == ("new", None)
    job.run_dir.mkdir(parents=True)
    (job.run_dir / "run.json").write_text(json.dumps({"argv": job.train_args()[1:] + ["--trainer.resume", "x"]}))
    assert run_state(job.run_dir, job.identity()) == ("partial", None)
    (job.run_dir / "checkpoints").mkdir()
    for s in (50, 100):
        (job.run_dir / "checkpoints" / f"step-{s:06d}.pt").write_bytes(b"")
    assert run_state(job.run_dir, job.identity()) == ("resume", 100)
    _write_metrics(job.run_dir, [{"step": 100, "wall": 1.0, "eval": {}, "final": True}])
    assert run_state(job.run_dir, job.identity()) == ("finished", 100)
    (job.run_dir / "run.json").write_text(json.dumps({"argv": job.train_args()[1:] + ["--method.x", "1"]}))
    assert run_state(job.run_dir, job.identity()) == ("changed", None)


def test_generated_scene_with_other_options_is_not_reused(tmp_path):
    from omnire_batch.runner import prepare_scene
    from omnire_batch.spec import Scene

    data = tmp_path / "scenes" / "u"
    (data / "ego_pose").mkdir(parents=True)
    scene = Scene("u", "processed", data, (), "urban", ("--frames", "30"))
    assert prepare_scene(scene, tmp_path / "logs") is None  # a scene put there by hand is used
    (tmp_path / "scenes" / ".u.synth.json").write_text(json.dumps({"preset": "urban", "args": ["--frames", "30"]}))
    assert prepare_scene(scene, tmp_path / "logs") is None
    other = Scene("u", "processed", data, (), "urban", ("--frames", "40"))
    assert "was generated with" in prepare_scene(other, tmp_path / "logs")
