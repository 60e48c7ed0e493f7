"""``omnire batch``: the command. Plans the jobs (skip finished, resume interrupted), runs the
rest on Ray with a progress display, records each result and writes the report."""
from __future__ import annotations

import json
import shlex
import time
from typing import Optional

import tyro

from omnire.api import ConfigError, UserError, atomic_write_text, check_location, load_json, writing
from omnire_batch.jobs import (
    BatchArgs,
    Job,
    args_with_toml,
    build_jobs,
    config_path_in,
    load_toml,
    resolve_path,
)
from omnire_batch.runs import run_state


def _load_record(job: Job) -> Optional[dict]:
    try:
        return json.loads(job.record_path.read_text())
    except (OSError, ValueError):
        return None


def _meta(args: BatchArgs, jobs: list[Job], argv: list[str]) -> dict:
    scenes = {j.scene.name: j.scene for j in jobs}
    return {
        "command": "omnire batch " + shlex.join(argv), "output": str(resolve_path(args.output)),
        "steps": args.steps, "seconds": args.seconds, "checkpoints": args.checkpoints,
        "seeds": list(args.seeds), "method_args": args.method_args,
        "scenes": [{"name": s.name, "dataparser": s.dataparser, "data": str(s.data), "args": list(s.args),
                    "synth": s.synth, "synth_args": list(s.synth_args)} for s in scenes.values()],
        "methods": sorted({j.label for j in jobs}, key=[j.label for j in jobs].index),
    }


def plan(jobs: list[Job], retry_failed: bool) -> list[tuple[Job, str, Optional[dict]]]:
    """(job, what to do, earlier record) for each job. What to do: "done" / "failed" (skipped),
    "changed", "run", "resume N" (when the run directory is visible here)."""
    out = []
    for job in jobs:
        rec = _load_record(job)
        if rec is not None and rec.get("command") != job.identity():
            out.append((job, "changed", rec))
            continue
        if rec is not None and rec.get("status") == "ok":
            out.append((job, "done", rec))
            continue
        if rec is not None and rec.get("status") == "failed" and not retry_failed:
            out.append((job, "failed", rec))
            continue
        state, step = run_state(job.run_dir, job.identity())
        what = {"resume": f"resume {step}", "changed": "changed", "finished": "collect"}.get(state, "run")
        out.append((job, what, rec))
    return out


class Display:
    """Progress across jobs: live bars on a terminal, a status line every 30 s otherwise."""

    def __init__(self, console, total: int) -> None:
        self.console, self.total, self.finished = console, total, 0
        self.live = console.is_terminal
        self.last_line = time.monotonic()
        self.bars: dict[str, int] = {}
        if self.live:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console)
            self.overall = self.progress.add_task("[bold]jobs[/]", total=total, info="")
            self.progress.start()

    def print(self, text: str) -> None:
        self.console.print(text, markup=False, highlight=False, soft_wrap=True)

    def result(self, r: dict) -> None:
        self.finished += 1
        if self.live:
            self.progress.update(self.overall, completed=self.finished)
            if r["job"] in self.bars:
                self.progress.remove_task(self.bars.pop(r["job"]))
        self.print(f"[{self.finished}/{self.total}] {describe(r)}")
        if r["status"] == "failed":
            self.print("    " + "\n    ".join(str(r.get("error", "")).splitlines()[1:][-15:]))

    def update(self, snapshot: dict, pending: list[str]) -> None:
        running = {k: v for k, v in snapshot.items() if k in pending and v.get("state") == "running"}
        if self.live:
            for key, info in running.items():
                if key not in self.bars:
                    self.bars[key] = self.progress.add_task(key, total=info.get("max_steps") or 1, info="")
                extra = f"{info['its']:.1f} it/s, psnr {info['psnr']:.1f}" if info.get("its") and info.get("psnr") else ""
                if info.get("resumed_from"):
                    extra += f" (resumed at {info['resumed_from']})"
                self.progress.update(self.bars[key], completed=info.get("step") or 0, info=extra)
        elif time.monotonic() - self.last_line > 30 and running:
            self.last_line = time.monotonic()
            self.print(f"[{self.finished}/{self.total}] running: " + "; ".join(
                f"{k} step {v.get('step') or 0}/{v.get('max_steps')}" for k, v in running.items()))

    def close(self) -> None:
        if self.live:
            self.progress.stop()


def describe(r: dict) -> str:
    """One line about a job result."""
    if r["status"] == "ok":
        psnr = r.get("final", {}).get("novel_view.full_psnr")
        what = "already finished" if not r.get("ran") else f"ok in {r.get('elapsed_s', 0):.0f} s"
        resumed = f" (resumed from step {r['resumed_from']})" if r.get("resumed_from") is not None else ""
        score = f", NVS PSNR {psnr:.2f}" if isinstance(psnr, (int, float)) else ""
        return f"{r['job']}: {what}{resumed}, step {r.get('steps_done')}{score}"
    first = str(r.get("error", "")).splitlines()[:1]
    return f"{r['job']}: {r['status'].upper()} (exit {r.get('exit_code')}): {first[0] if first else ''}"


def main(argv: list[str], plugins) -> int:
    from rich.console import Console

    from omnire_batch.report import write_report

    console = Console()
    cfg = config_path_in(argv)
    data, src = load_toml(cfg) if cfg else ({}, None)
    defaults = args_with_toml(BatchArgs(), data, src) if src else BatchArgs()
    args = tyro.cli(BatchArgs, args=argv, default=defaults, prog="omnire batch")
    output = resolve_path(args.output)
    if args.report_only:
        path = output / "results.json"
        if not path.is_file():
            raise ConfigError(f"{path}: no results.json to report from (run without --report-only first)")
        saved = load_json(path, "batch results file")
        if not isinstance(saved, dict) or not {"results", "args"} <= set(saved):
            raise ConfigError(f"{path}: not a batch results file (expected an object with 'results' and 'args')")
        with writing(output, "cannot write the batch's report"):
            text = write_report(output, saved["results"], saved["args"], args.plot, console.print)
        console.print(text, markup=False, highlight=False, soft_wrap=True)
        return 0
    jobs = build_jobs(args, data, src, plugins)
    # the batch writes into --output (runs, logs, records, report): never into a dataset it reads
    check_location(output, "--output", sorted({j.scene.data for j in jobs if j.scene.synth is None}), replaces=False)
    steps = plan(jobs, args.retry_failed)
    changed = [j for j, what, _ in steps if what == "changed"]
    if changed and not args.redo_changed:
        raise ConfigError(f"{len(changed)} job(s) were run before with another command (budget or flags changed), "
                          f"e.g. {changed[0].key} ({changed[0].run_dir}); rerun with --redo-changed to move their "
                          "run directories to <output>/superseded/ and train them again, or use another --output")
    results: dict[str, dict] = {}
    to_run = []
    for job, what, rec in steps:
        if what in ("done", "failed"):
            results[job.key] = rec
        else:
            to_run.append(job)
    n_done = sum(w == "done" for _, w, _ in steps)
    n_failed = sum(w == "failed" for _, w, _ in steps)
    n_resume = sum(w.startswith("resume") for _, w, _ in steps)
    console.print(f"{len(jobs)} jobs in {output}: {n_done} done (skipped), {n_failed} failed before (skipped"
                  f"{'; --retry-failed runs them again' if n_failed else ''}), {len(to_run)} to run"
                  f" ({n_resume} resume from a checkpoint)", highlight=False)
    if args.dry_run:
        for job, what, _ in steps:
            console.print(f"  {job.key:<50} {what:<12} omnire {shlex.join(job.train_args())}", highlight=False,
                          soft_wrap=True)
        return 0
    meta = _meta(args, jobs, argv)

    def all_results() -> list[dict]:
        return [results.get(j.key) or dict(job=j.key, scene=j.scene.name, method=j.label, seed=j.seed,
                                           status="not run") for j in jobs]

    stopped = False
    if to_run:
        from omnire_batch import cluster
        from omnire_batch.report import write_results_json

        with writing(output, "cannot create the batch's output directory"):
            output.mkdir(parents=True, exist_ok=True)
        try:
            console.print(cluster.start_ray(args.address, args.local_cpus), highlight=False)
        except ConnectionError as exc:
            raise UserError(f"--address {args.address or _ray_address_env()}: no Ray cluster answers ({exc})") from exc
        try:
            problems = cluster.infeasible(to_run)
            if problems and not (args.address or _ray_address_env()):
                # a local instance never grows; a cluster's autoscaler may add a large enough node
                raise ConfigError("no node can run these jobs (lower --num-cpus/--num-gpus/--memory-gb, or raise "
                                  "--local-cpus): " + "; ".join(problems[:5]) + (" ..." if len(problems) > 5 else ""))
            for warning in problems:
                console.print(f"warning: {warning}", markup=False, highlight=False)
            display = Display(console, len(to_run))

            def on_result(r: dict) -> None:
                job = next(j for j in to_run if j.key == r["job"])
                results[job.key] = r
                with writing(output, "cannot write the batch's results"):
                    atomic_write_text(job.record_path, json.dumps(r, indent=2, default=str))
                    write_results_json(output, all_results(), meta)
                display.result(r)

            def on_stop(level: int) -> None:
                display.print("stopping: each running job writes a checkpoint and exits (a rerun resumes it); "
                              "signal again to stop at once" if level == 1 else "stopping at once")

            try:
                stopped = not cluster.BatchRun(to_run, args.redo_changed).run(on_result, display.update, on_stop)
            finally:
                display.close()
        finally:
            import ray

            ray.shutdown()
    final = all_results()
    with writing(output, "cannot write the batch's report"):
        text = write_report(output, final, meta, args.plot, console.print)
    console.print(text, markup=False, highlight=False, soft_wrap=True)
    bad = [r for r in final if r.get("status") != "ok"]
    for r in bad:
        if r.get("status") == "failed":
            console.print(f"failed: {r['job']}: " + "\n    ".join(str(r.get("error", "")).splitlines()[-16:]),
                          markup=False, highlight=False, soft_wrap=True)
    console.print(f"results: {output / 'results.md'}, {output / 'results.json'}", highlight=False)
    if stopped:
        return 130
    return 1 if bad else 0


def _ray_address_env() -> Optional[str]:
    import os

    return os.environ.get("RAY_ADDRESS")

