"""``omnire batch`` end to end: a real local Ray instance (2 CPUs), real ``omnire train``
subprocesses on a tiny synthetic scene, failures, reruns, and a batch killed mid-training."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from omnire.rundir import RunDirectory


def checkpoint_steps(run):
    return RunDirectory(run).checkpoint_steps()


def read_metrics(run):
    return RunDirectory(run).read_metrics()

SMALL = "--method.nodes.background.max-lidar-points 2000 --method.nodes.background.num-far-points 200"
ENV = dict(os.environ, COLUMNS="200", OMP_NUM_THREADS="1")


def batch(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "omnire.cli", "batch", "--local-cpus", "2", *args],
                          capture_output=True, text=True, timeout=timeout, env=ENV)


def test_failing_job_is_reported_others_finish_and_a_rerun_runs_nothing(tmp_path):
    out = tmp_path / "out"
    config = tmp_path / "tiny.toml"
    config.write_text(f"""
output = "{out}"
steps = 40
checkpoints = 2
method_args = "{SMALL}"

[[scene]]
name = "tiny"
synth = "empty"          # generated once by a Ray task before the jobs
synth_args = "--tiny"
args = "--holdout-every 4"

[[method]]
name = "3dgs"

[[method]]
name = "3dgs-dim"
method = "3dgs"
args = "--method.nodes.background.init-opacity 0.05"

[[method]]
name = "broken"
method = "3dgs"
args = "--method.no-such-flag 1"
""")
    first = batch("--config", str(config))
    text = first.stdout + first.stderr
    assert first.returncode == 1, text  # one job failed
    assert "3 jobs" in text and "3 to run" in text and "local Ray instance" in text
    assert "tiny/broken-seed0: FAILED (exit 2)" in text
    assert "no-such-flag" in text  # the log tail of the failed job
    saved = json.loads((out / "results.json").read_text())
    by_label = {r["method"]: r for r in saved["results"]}
    assert by_label["broken"]["status"] == "failed" and "no-such-flag" in by_label["broken"]["error"]
    for label in ("3dgs", "3dgs-dim"):
        r = by_label[label]
        assert r["status"] == "ok" and r["steps_done"] == 40 and r["ran"], r
        assert [c["step"] for c in r["curve"]] == [20, 40]  # one evaluation on the way, the final one
        assert r["final"]["novel_view.views"] > 0 and r["final"]["novel_view.full_psnr"] > 5
        assert sorted(checkpoint_steps(out / "runs" / "tiny" / f"{label}-seed0")) == [20, 40]
    assert saved["summary"]["methods"]["3dgs"]["novel_view.full_psnr"]["n"] == 1
    # 1 CPU each on 2 CPUs: never three trainers at once
    events = sorted([(r["started_at"], 1) for r in saved["results"]] + [(r["ended_at"], -1) for r in saved["results"]])
    running = [sum(d for _, d in events[:i + 1]) for i in range(len(events))]
    assert max(running) <= 2, events
    md = (out / "results.md").read_text()
    assert "### Across scenes and seeds" in md and "| 3dgs | 1/1 |" in md and "| broken | 0/1 |" in md
    assert "| broken | failed (exit 2) |" in md  # omnire bench train's per-scene table
    assert (out / "psnr_vs_time.png").stat().st_size > 1000 and (out / "plots" / "tiny.png").is_file()

    logs = {p: p.stat().st_mtime_ns for p in (out / "logs").rglob("*.log")}
    metrics = {p: p.read_bytes() for p in (out / "runs").rglob("metrics.jsonl")}
    again = batch("--config", str(config))
    text = again.stdout + again.stderr
    assert again.returncode == 1, text  # still one failed job, reported again
    assert "1 failed before (skipped" in text and "2 done (skipped)" in text and "0 to run" in text
    assert "local Ray instance" not in text  # nothing to run: Ray is not even started
    assert "failed: tiny/broken-seed0" in text and "no-such-flag" in text
    assert {p: p.stat().st_mtime_ns for p in (out / "logs").rglob("*.log")} == logs
    assert {p: p.read_bytes() for p in (out / "runs").rglob("metrics.jsonl")} == metrics
    assert json.loads((out / "results.json").read_text())["results"] == saved["results"]


def _wait_for_checkpoints(run: Path, proc: subprocess.Popen, above: int, deadline_s: float = 300) -> list[int]:
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        steps = checkpoint_steps(run)
        if any(s > above for s in steps):
            return steps
        assert proc.poll() is None, proc.communicate()[0]
        time.sleep(0.1)
    proc.kill()
    raise AssertionError(f"no checkpoint past step {above} in {run} after {deadline_s} s")


def _trainer_pid(run: Path) -> int:
    """The pid of the ``omnire train`` process writing ``run`` (started by this test's batch)."""
    needle = f"--trainer.output-dir\x00{run.parent}\x00--trainer.run-name\x00{run.name}\x00".encode()
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and needle in (proc / "cmdline").read_bytes():
                return int(proc.name)
        except OSError:
            continue
    raise AssertionError(f"no trainer process for {run}")


def test_killed_batch_resumes_from_the_newest_checkpoint(tmp_path):
    """SIGTERM to the batch (it asks its jobs to stop), SIGTERM to the job's trainer, then SIGKILL
    of the batch process, each mid-training: every rerun continues the job from its newest
    checkpoint instead of starting again."""
    out = tmp_path / "out"
    # 320x200 images: a tiny 72x48 scene trains ~300 steps/s, fast enough to finish inside the
    # driver's reaction time to a signal (it polls once a second)
    args = ["--scenes", "tiny=synth:empty --frames 8 --width 320 --height 200", "--methods", "3dgs", "--steps", "1200",
            "--checkpoints", "1",
            "--checkpoint-every", "50", f"--method-args={SMALL}", "--output", str(out)]
    run = out / "runs" / "tiny" / "3dgs-seed0"
    cmd = [sys.executable, "-m", "omnire.cli", "batch", "--local-cpus", "2", *args]

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    _wait_for_checkpoints(run, proc, 0)
    proc.send_signal(signal.SIGTERM)
    text = proc.communicate(timeout=120)[0]
    assert proc.returncode == 130, text
    job_log = out / "logs" / "tiny" / "3dgs-seed0.log"
    assert "stopping: each running job writes a checkpoint" in text and "INTERRUPTED" in text, (
        text + "\n--- job log tail ---\n" + (job_log.read_text()[-3000:] if job_log.is_file() else "(none)"))
    record = json.loads((out / "jobs" / "tiny" / "3dgs-seed0.json").read_text())
    assert record["status"] == "interrupted"
    first = checkpoint_steps(run)
    assert 0 < first[-1] < 1200

    # Second attempt resumes; SIGTERM its trainer directly (as an OOM killer or an admin
    # would): the job is interrupted, not failed, and the batch goes on to its end.
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    _wait_for_checkpoints(run, proc, first[-1])
    os.kill(_trainer_pid(run), signal.SIGTERM)
    text = proc.communicate(timeout=120)[0]
    assert "1 to run (1 resume from a checkpoint)" in text, text
    assert proc.returncode == 1 and "tiny/3dgs-seed0: INTERRUPTED" in text, text
    second = checkpoint_steps(run)
    assert second[-1] > first[-1]

    # Third attempt resumes; kill the batch process outright once it has gone further.
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    _wait_for_checkpoints(run, proc, second[-1])
    proc.kill()
    text = proc.communicate(timeout=30)[0]
    assert "1 to run (1 resume from a checkpoint)" in text, text

    # The orphaned trainer gets SIGTERM when its Ray worker dies, which Ray may take a while
    # to notice: on a loaded machine a tiny job can even finish first. Wait until it is gone.
    deadline = time.time() + 120
    while time.time() < deadline:
        try:
            _trainer_pid(run)
        except AssertionError:
            break
        time.sleep(0.5)
    orphan_finished = RunDirectory(run).results() is not None
    before = {s: (run / "checkpoints" / f"step-{s:06d}.pt").stat().st_mtime_ns for s in checkpoint_steps(run)}
    newest = max(before)
    assert newest > first[-1]
    started = time.time_ns()
    last = batch(*args, timeout=600)
    text = last.stdout + last.stderr
    assert last.returncode == 0, text
    result = json.loads((out / "results.json").read_text())["results"][0]
    assert result["status"] == "ok" and result["steps_done"] == 1200
    if orphan_finished:  # nothing was left to resume: the rerun ran nothing
        assert result["resumed_from"] is None
        return
    assert result["resumed_from"] is not None and result["resumed_from"] >= newest, (result["resumed_from"], newest)
    resumed = result["resumed_from"]
    for step, mtime in before.items():  # what came before the resume point was not redone
        if step <= resumed:
            assert (run / "checkpoints" / f"step-{step:06d}.pt").stat().st_mtime_ns == mtime < started
    assert all((run / "checkpoints" / f"step-{s:06d}.pt").stat().st_mtime_ns >= started
               for s in checkpoint_steps(run) if s > resumed)
    log = (out / "logs" / "tiny" / "3dgs-seed0.log").read_text()
    headers = [line for line in log.splitlines() if line.startswith("=== ")]
    assert len(headers) == 4 and "(new run)" in headers[0]
    assert f"(resuming from step {first[-1]})" in headers[1] and f"(resuming from step {second[-1]})" in headers[2]
    assert f"(resuming from step {resumed})" in headers[3]
    steps = [r["step"] for r in read_metrics(run) if "its" in r]
    assert steps == sorted(set(steps)) and steps[-1] == 1200 and steps[0] <= 50


def test_stop_file_interrupts_running_jobs(tmp_path):
    """The path that does not depend on Ray's KeyboardInterrupt: a job task that sees
    <output>/.stop-requested has its trainer checkpoint and exit (interrupted, resumable)."""
    from omnire_batch.cluster import STOP_FILE

    out = tmp_path / "out"
    out.mkdir()
    (out / STOP_FILE).touch()  # left over by an earlier stopped batch: removed at the start
    args = ["--scenes", "tiny=synth:empty --frames 8 --width 320 --height 200", "--methods", "3dgs", "--steps", "1200",
            "--checkpoints", "1", "--checkpoint-every", "50", f"--method-args={SMALL}", "--output", str(out)]
    run = out / "runs" / "tiny" / "3dgs-seed0"
    proc = subprocess.Popen([sys.executable, "-m", "omnire.cli", "batch", "--local-cpus", "2", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    _wait_for_checkpoints(run, proc, 0)
    (out / STOP_FILE).touch()
    text = proc.communicate(timeout=120)[0]
    assert proc.returncode == 1 and "tiny/3dgs-seed0: INTERRUPTED" in text, text
    assert json.loads((out / "jobs" / "tiny" / "3dgs-seed0.json").read_text())["status"] == "interrupted"
    assert 0 < checkpoint_steps(run)[-1] < 1200
    assert not (out / STOP_FILE).exists()
