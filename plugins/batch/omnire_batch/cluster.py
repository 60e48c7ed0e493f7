"""The Ray side: start or join Ray, submit scene preparations and jobs as tasks with their
resources, follow their progress and stop them cleanly.

Each job is one Ray task reserving its CPUs, GPUs and memory; inside it
``omnire_batch.runner.execute_job`` runs ``omnire train`` as a subprocess. A small actor (no
CPU) carries progress from the tasks to the driver; stopping is ``ray.cancel``, which raises
KeyboardInterrupt in a running task (the job then has its trainer checkpoint and exit).
Nothing here needs storage shared with the driver. Nothing here imports torch or the omnire
core either: workers unpickle these functions and start fast.
"""
from __future__ import annotations

import logging
import os
import signal
import time
from typing import Callable, Optional

import ray

from omnire_batch.spec import Job, Scene
from omnire_batch.runner import base_result, execute_job, prepare_scene

GIB = 1024 ** 3
STOP_FILE = ".stop-requested"
"""Created in the batch output folder when the driver is asked to stop: each job task sees it
within a second and has its trainer checkpoint and exit. ray.cancel does the same through a
KeyboardInterrupt in the task, which a task blocked in a system call can miss (observed: a
job ran to its end); the file is the path that does not depend on it (the output folder is
on storage every worker sees, docs/batch.md)."""


@ray.remote(num_cpus=0)
class ProgressBoard:
    """Latest progress of each job (the tasks write, the driver reads)."""

    def __init__(self) -> None:
        self.state: dict[str, dict] = {}

    def report(self, key: str, info: dict) -> None:
        self.state[key] = dict(info, time=time.time())

    def snapshot(self) -> dict:
        return self.state


@ray.remote
def _prepare_task(scene: Scene, log_dir) -> Optional[str]:
    try:
        return prepare_scene(scene, log_dir)
    except Exception as exc:  # reported on each job of the scene instead of an opaque RayTaskError
        return f"preparing scene {scene.name!r} failed: {type(exc).__name__}: {exc}"


@ray.remote
def _job_task(job: Job, scene_error: Optional[str], redo_changed: bool, board) -> dict:
    stop_file = job.output / STOP_FILE

    def report(key: str, info: dict) -> bool:
        # Fire and forget: a task blocked in ray.get lends its CPUs to other tasks, which
        # would start more trainers than there are cores. True = stop (see STOP_FILE).
        board.report.remote(key, info)
        return stop_file.exists()

    return execute_job(job, report, scene_error, redo_changed)


def start_ray(address: Optional[str], local_cpus: int) -> str:
    """Join ``address`` (or RAY_ADDRESS), else start a local Ray instance; returns a description."""
    address = address or os.environ.get("RAY_ADDRESS")
    quiet = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    if address:
        ray.init(address=address, **quiet)  # ConnectionError when nothing answers there
    else:
        # Ray runs workers at nice 15 by default; on a local instance the jobs are the work,
        # and their it/s should compare with `omnire bench train` (RAY_worker_niceness overrides).
        os.environ.setdefault("RAY_worker_niceness", "0")
        ray.init(address="local", num_cpus=local_cpus or None, **quiet)
    res = ray.cluster_resources()
    where = f"Ray cluster at {address}" if address else "local Ray instance"
    return (f"{where}: {len([n for n in ray.nodes() if n.get('Alive')])} node(s), {res.get('CPU', 0):g} CPUs, "
            f"{res.get('GPU', 0):g} GPUs, {res.get('memory', 0) / GIB:.1f} GiB")


def infeasible(jobs: list[Job]) -> list[str]:
    """Jobs whose resources no single alive node has, described."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    problems = []
    for job in jobs:
        need = {"CPU": job.num_cpus, "GPU": job.num_gpus, "memory": job.memory_gb * GIB}
        if not any(all(n.get(k, 0) >= v for k, v in need.items() if v > 0) for n in nodes):
            best = {k: max((n.get(k, 0) for n in nodes), default=0) for k in need}
            problems.append(f"{job.key} asks for {job.num_cpus:g} CPUs, {job.num_gpus:g} GPUs, {job.memory_gb:g} GiB; "
                            f"the largest node has {best['CPU']:g} CPUs, {best['GPU']:g} GPUs, "
                            f"{best['memory'] / GIB:.1f} GiB")
    return problems


class BatchRun:
    """Submit ``jobs`` and follow them until each has a result.

    ``on_result(result)`` is called in the driver as each job ends; ``on_progress(snapshot,
    pending keys)`` about once a second. SIGINT/SIGTERM ask every job to checkpoint and stop
    (it then reports "interrupted"); a second signal kills the workers.
    """

    def __init__(self, jobs: list[Job], redo_changed: bool = False) -> None:
        self.jobs = jobs
        self.redo_changed = redo_changed
        self.signals = 0

    def _on_signal(self, signum, frame) -> None:
        self.signals += 1

    def run(self, on_result: Callable[[dict], None], on_progress: Callable[[dict, list[str]], None],
            on_stop: Callable[[int], None]) -> bool:
        """Returns False when a signal stopped the batch (it came while jobs were running)."""
        stop_file = self.jobs[0].output / STOP_FILE
        stop_file.unlink(missing_ok=True)  # left by an earlier batch that was stopped
        board = ProgressBoard.remote()
        log_dir = self.jobs[0].output / "logs"
        ready: dict[str, ray.ObjectRef] = {}
        for job in self.jobs:
            if job.scene.synth is not None and job.scene.name not in ready:
                ready[job.scene.name] = _prepare_task.options(num_cpus=1, name=f"prepare {job.scene.name}").remote(
                    job.scene, log_dir)
        pending: dict[ray.ObjectRef, Job] = {}
        for job in self.jobs:
            opts = dict(num_cpus=job.num_cpus, num_gpus=job.num_gpus, name=job.key, max_retries=2)
            if job.memory_gb > 0:
                opts["memory"] = int(job.memory_gb * GIB)
            ref = _job_task.options(**opts).remote(job, ready.get(job.scene.name), self.redo_changed, board)
            pending[ref] = job
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        handled = 0  # signals acted on; one that arrives after the last job ended stops nothing
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=len(pending), timeout=1.0)
                for ref in done:
                    job = pending.pop(ref)
                    on_result(self._get(ref, job, stopping=self.signals > 0))
                if self.signals > handled:
                    handled = self.signals
                    on_stop(min(handled, 2))
                    stop_file.touch()
                    # 1st signal: KeyboardInterrupt in running tasks (their trainers checkpoint and
                    # exit; queued tasks are dropped); 2nd: kill the workers (trainers get SIGTERM).
                    for ref in pending:
                        ray.cancel(ref, force=handled > 1)
                try:
                    snap = ray.get(board.snapshot.remote(), timeout=10)
                except Exception:
                    snap = {}
                on_progress(snap, [j.key for j in pending.values()])
        finally:
            for s, h in old.items():
                signal.signal(s, h)
            stop_file.unlink(missing_ok=True)
        return handled == 0

    @staticmethod
    def _get(ref, job: Job, stopping: bool) -> dict:
        resume = "; a rerun resumes it from its newest checkpoint"
        try:
            return ray.get(ref)
        except ray.exceptions.TaskCancelledError:
            return dict(base_result(job), status="interrupted", exit_code=None, ran=True,
                        error="stopped by the batch" + resume)
        except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as exc:
            # a crash while stopping is the stop; otherwise Ray's retries (each resuming) ran out
            status = "interrupted" if stopping else "failed"
            return dict(base_result(job), status=status, exit_code=None, ran=True,
                        error=f"{type(exc).__name__}: {str(exc)[-1500:]}" + (resume if status == "interrupted" else ""))
        except ray.exceptions.RayError as exc:
            return dict(base_result(job), status="failed", exit_code=None, ran=True,
                        error=f"{type(exc).__name__}: {str(exc)[-3000:]}")
