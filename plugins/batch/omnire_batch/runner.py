"""One job on a worker: ``omnire train`` in a subprocess, resumed or skipped as its run directory says.

Runs inside a Ray task (``omnire_batch.cluster``) but needs no Ray itself: progress and the
batch's stop request go through the ``report`` callable. The subprocess uses the worker's own
Python (``sys.executable -m omnire.cli``), so each worker needs omnire and the plugins of the
batch's methods and dataparsers installed, and the data at the path the batch names.
"""
from __future__ import annotations

import ctypes
import fcntl
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Optional

from omnire_batch.spec import Job, Scene
from omnire.rundir import RunDirectory
from omnire_batch.runs import run_state

Report = Callable[[str, dict], bool]
"""report(job key, progress info) -> whether the batch asks the job to stop."""

STOP_GRACE_S = 300.0
"""After SIGTERM, how long a trainer may take to write its checkpoint before SIGKILL."""
LOCK_WAIT_S = 120.0
"""How long a job waits for a previous attempt of itself (e.g. an orphan still writing its last
checkpoint after its batch was killed) to let go of the run directory."""
TAIL_LINES = 40
INTERRUPTED_RE = re.compile(r"\b(SIGTERM|SIGINT|SIGHUP): stopped at step \d+; checkpoint")
"""How the trainer reports a signal it stopped on (it exits 2, as for any user error): the
job is resumable, not failed."""


try:  # resolved here: the child of a threaded worker must not load libraries between fork and exec
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):
    _PRCTL = None


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the worker that started it dies (Linux), so a
    killed batch does not leave trainers running (and they checkpoint on SIGTERM)."""
    if _PRCTL is not None:
        _PRCTL(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG


def _env(threads: int) -> dict:
    t = str(max(1, threads))
    return dict(os.environ, OMP_NUM_THREADS=t, MKL_NUM_THREADS=t, COLUMNS="200", PYTHONUNBUFFERED="1")


def scene_present(path: Path) -> bool:
    """A processed-layout scene is there (what the synthetic dataparser checks too)."""
    return (Path(path) / "ego_pose").is_dir() or (Path(path) / "lidar_pose").is_dir()


def prepare_scene(scene: Scene, log_dir: Path) -> Optional[str]:
    """Generate a synthetic scene once (``omnire synth``) unless its folder holds one already;
    None when ready, else the error with the log tail. Generated beside the target and renamed
    into place, so concurrent or killed preparations never leave a half-written scene. The
    options are recorded beside it (``.<name>.synth.json``): a scene generated with other
    options is an error, not silently reused."""
    if scene.synth is None:
        return None
    data = Path(scene.data)
    marker = data.parent / f".{data.name}.synth.json"
    options = {"preset": scene.synth, "args": list(scene.synth_args)}
    if scene_present(data):
        try:
            made = json.loads(marker.read_text())
        except (OSError, ValueError):
            return None  # a scene put there by hand: use it
        if made != options:
            return (f"{data} was generated with {made}, the batch asks for {options}: delete the folder "
                    f"(and {marker.name}) to generate it again, or name the scene differently")
        return None
    data.parent.mkdir(parents=True, exist_ok=True)
    tmp = data.parent / f".{data.name}.partial-{socket.gethostname()}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    log = Path(log_dir) / scene.name / "synth.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "omnire.cli", "synth", scene.synth, str(tmp), *scene.synth_args]
    with open(log, "a") as out:
        out.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} on {socket.gethostname()}: {' '.join(cmd[2:])}\n")
        out.flush()
        start = out.tell()
        rc = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, env=_env(1), stdin=subprocess.DEVNULL,
                            preexec_fn=_die_with_parent).returncode
    if rc != 0:
        shutil.rmtree(tmp, ignore_errors=True)
        return f"`omnire synth {scene.synth}` for scene {scene.name!r} failed (exit {rc}); log {log}:\n" + \
            log_tail(log, start)
    atomic_write_json(marker, options)
    try:
        os.rename(tmp, data)  # replaces an empty folder; fails if another worker got there first
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if not scene_present(data):
            return f"cannot move the generated scene into {data}: {exc}"
    return None


def atomic_write_json(path: Path, value) -> None:
    """Temp file + rename (the core's atomic writer would import torch into the worker)."""
    tmp = path.parent / f".{path.name}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(value))
    os.replace(tmp, path)


def log_tail(path: Path, start: int = 0, lines: int = TAIL_LINES) -> str:
    """The last ``lines`` lines of ``path`` after byte ``start`` (this attempt's output)."""
    try:
        with open(path, "rb") as f:
            f.seek(start)
            text = f.read().decode("utf-8", errors="replace")
    except OSError:
        return ""
    return "\n".join(text.rstrip().splitlines()[-lines:])


class _MetricsTail:
    """The newest training record of a growing ``metrics.jsonl`` (for the progress display)."""

    def __init__(self, path: Path) -> None:
        self.path, self.offset, self.rest, self.latest = path, 0, "", {}

    def poll(self) -> dict:
        try:
            with open(self.path, "r", errors="replace") as f:
                f.seek(self.offset)
                chunk = f.read()
                self.offset = f.tell()
        except OSError:
            return self.latest
        lines = (self.rest + chunk).split("\n")
        self.rest = lines.pop()
        for line in lines:
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(r, dict) and "its" in r:
                self.latest = {"step": r.get("step"), "its": r.get("its"), "psnr": r.get("psnr"),
                               "gaussians": r.get("num_gaussians")}
        return self.latest


def _lock(path: Path, wait_s: float):
    """An exclusive flock on ``path`` (held by this worker and its trainer); None if another
    process keeps it longer than ``wait_s``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    f = open(path, "a")
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            return f
        except BlockingIOError:
            if time.monotonic() > deadline:
                f.close()
                return None
            time.sleep(0.5)


def base_result(job: Job) -> dict:
    """The fields every job result has (the row keys of ``omnire bench train`` plus batch ones)."""
    return {"job": job.key, "scene": job.scene.name, "method": job.label, "base_method": job.method.method,
            "variant": job.variant.name, "flags": job.flags, "seed": job.seed, "command": job.identity(),
            "run_dir": str(job.run_dir), "log": str(job.log_path), "node": socket.gethostname(),
            "resources": {"num_cpus": job.num_cpus, "num_gpus": job.num_gpus, "memory_gb": job.memory_gb,
                          "threads": job.threads}}


def execute_job(job: Job, report: Optional[Report] = None, scene_error: Optional[str] = None,
                redo_changed: bool = False, stop_grace_s: float = STOP_GRACE_S,
                lock_wait_s: float = LOCK_WAIT_S) -> dict:
    """Run (or resume, or skip) one job; returns its result. ``status`` is "ok" (with
    ``curve``/``final``/``steps_done``/``train_its``), "failed" (``error`` holds the reason and
    the log tail) or "interrupted" (stopped by the batch or killed by a signal: a rerun
    resumes it). ``ran`` says whether a trainer was started."""
    t0 = time.monotonic()
    result = base_result(job)
    result.update(status="failed", exit_code=None, elapsed_s=0.0, ran=False, resumed_from=None,
                  started_at=time.time())

    def done(**kw) -> dict:
        result.update(kw, elapsed_s=time.monotonic() - t0, ended_at=time.time())
        return result

    def say(info: dict) -> bool:
        if report is None:
            return False
        try:
            return bool(report(job.key, info))
        except Exception:  # the batch (driver) is gone: stop and keep the checkpoint
            return True

    if scene_error:
        return done(error=scene_error)
    if say({"state": "waiting"}):
        return done(status="interrupted", error="stopped by the batch before it started")
    lock = _lock(job.run_dir.parent / f".{job.name}.lock", lock_wait_s)
    if lock is None:  # transient: the next rerun tries again
        return done(status="interrupted", error=f"{job.run_dir}: another process holds its lock (an earlier "
                                                  "attempt still running?); rerun when it has stopped")
    try:
        return _execute_locked(job, result, done, say, redo_changed, stop_grace_s, lock)
    finally:
        lock.close()


def _supersede(job: Job) -> Path:
    """Move the job's run directory to ``<output>/superseded/<time>/<scene>/<name>``."""
    dest = job.output / "superseded" / time.strftime("%Y%m%d-%H%M%S") / job.scene.name / job.name
    dest.parent.mkdir(parents=True, exist_ok=True)
    os.replace(job.run_dir, dest)
    return dest


def _execute_locked(job: Job, result: dict, done, say, redo_changed: bool, stop_grace_s: float, lock) -> dict:
    identity = job.identity()
    state, step = run_state(job.run_dir, identity)
    if state == "changed":
        if not redo_changed:
            return done(error=f"{job.run_dir}: made by a different command (budget or flags changed); "
                              "rerun with --redo-changed to move it to <output>/superseded/ and train again")
        _supersede(job)
        state, step = "new", None
    if state == "finished":
        return done(status="ok", exit_code=0, **RunDirectory(job.run_dir).results())
    if state == "partial":  # nothing to resume from; the trainer refuses an existing directory
        _supersede(job)  # moved aside, not deleted: a run directory is never removed
    cmd = [sys.executable, "-m", "omnire.cli", *job.train_args()]
    if state == "resume":
        cmd += ["--trainer.resume", str(job.run_dir)]
        result["resumed_from"] = step
    job.log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(job.log_path, "a") as log:
        how = f"resuming from step {step}" if state == "resume" else "new run"
        log.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} on {socket.gethostname()} ({how}): "
                  f"{' '.join(cmd[2:])}\n")
        log.flush()
        start = log.tell()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=_env(job.threads), preexec_fn=_die_with_parent, start_new_session=True,
                                pass_fds=(lock.fileno(),))  # the trainer holds the lock until it exits
    result["ran"] = True
    stop_reason, kill_at = None, None
    metrics = _MetricsTail(job.run_dir / "metrics.jsonl")
    started = time.monotonic()
    try:
        while True:
            try:
                rc = proc.wait(timeout=1.0)
                break
            except subprocess.TimeoutExpired:
                pass
            info = {"state": "running", "max_steps": job.steps, "resumed_from": step if state == "resume" else None,
                    **metrics.poll()}
            wants_stop = say(info)
            if stop_reason is None and wants_stop:
                stop_reason = "stopped by the batch"
            elif stop_reason is None and job.timeout and time.monotonic() - started > job.timeout:
                stop_reason = f"stopped after {job.timeout:.0f} s (job timeout)"
            if stop_reason is not None and kill_at is None:
                proc.send_signal(signal.SIGTERM)  # the trainer checkpoints and exits
                kill_at = time.monotonic() + stop_grace_s
            elif kill_at is not None and time.monotonic() > kill_at:
                proc.kill()
    except BaseException:  # cancelled (KeyboardInterrupt in the task) or worker exiting
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=stop_grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
        raise
    tail = log_tail(job.log_path, start)
    if rc == 0 and stop_reason is None:
        res = RunDirectory(job.run_dir).results()
        if res is not None:
            return done(status="ok", exit_code=0, **res)
        return done(exit_code=0, error=f"omnire train exited 0 but {job.run_dir}/metrics.jsonl has no final "
                                       f"evaluation; log {job.log_path}:\n{tail}")
    if stop_reason == "stopped by the batch" or (stop_reason is None and (rc < 0 or rc in (130, 143)
                                                                          or INTERRUPTED_RE.search(tail))):
        why = stop_reason or (f"killed by signal {-rc}" if rc < 0 else f"interrupted (exit {rc})")
        return done(status="interrupted", exit_code=rc, error=f"{why}; a rerun resumes it from its newest checkpoint")
    why = stop_reason or f"omnire train exited with {rc}"
    return done(exit_code=rc, error=f"{why}; log {job.log_path}:\n{tail}")
