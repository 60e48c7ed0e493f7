"""Reading a run directory: its state for a rerun, and its results in ``omnire bench train``'s form.

A run directory (``omnire train``) holds ``run.json`` (the train arguments), ``metrics.jsonl``
(one record per logged step / evaluation; the last one is ``"final": true`` once training and
its final evaluation are done) and ``checkpoints/step-NNNNNN.pt``.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Optional

from omnire_batch.spec import strip_flags

CHECKPOINT_RE = re.compile(r"^step-(\d+)\.pt$")


def checkpoint_steps(run_dir: Path) -> list[int]:
    """Steps of the checkpoints in ``run_dir/checkpoints``, ascending."""
    folder = Path(run_dir) / "checkpoints"
    if not folder.is_dir():
        return []
    return sorted(int(m.group(1)) for p in folder.iterdir() if (m := CHECKPOINT_RE.match(p.name)))


def read_metrics(run_dir: Path) -> list[dict]:
    """The records of ``metrics.jsonl`` as one uninterrupted run would have written them.

    A resumed run continues from its checkpoint: records past the checkpoint's step that an
    interrupted attempt left (when the trainer appended instead of truncating) are dropped where
    the steps go back, and training wall time, which a resumed trainer may restart from zero,
    is offset so that it keeps growing across attempts (by the time of the last kept record,
    i.e. exact when checkpoints fall on logged steps). Unparsable lines (a write cut by a
    kill) are skipped.
    """
    path = Path(run_dir) / "metrics.jsonl"
    if not path.is_file():
        return []
    out: list[dict] = []
    offset = 0.0
    for line in path.read_text(errors="replace").splitlines():
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not isinstance(r, dict) or not isinstance(r.get("step"), int):
            continue
        r = dict(r)
        raw_wall = float(r.get("wall", 0.0))
        if out:
            prev = out[-1]
            same_kind = ("eval" in r) == ("eval" in prev)
            went_back = r["step"] < prev["step"] or (r["step"] == prev["step"] and same_kind)
            if went_back:  # a new attempt after a resume: keep what precedes its first step
                out = [p for p in out if p["step"] < r["step"]]
                kept = out[-1]["wall"] if out else 0.0
                offset = kept if raw_wall < kept else 0.0  # 0: the trainer restored its clock
            elif raw_wall + offset < prev["wall"] - 1e-9:  # same steps onwards, wall restarted
                offset = prev["wall"]
        r["wall"] = raw_wall + offset
        out.append(r)
    return out


def flatten_eval(ev: dict) -> dict:
    """An evaluation record -> one flat dict: top-level numbers plus ``reconstruction.*`` and
    ``novel_view.*`` (the keys ``omnire bench train`` tables and plots read)."""
    flat = {k: v for k, v in ev.items() if not isinstance(v, dict)}
    for split in ("reconstruction", "novel_view"):
        for k, v in (ev.get(split) or {}).items():
            if not isinstance(v, dict):
                flat[f"{split}.{k}"] = v
    return flat


def run_results(run_dir: Path) -> Optional[dict]:
    """``curve`` (one entry per evaluation: step, train_seconds, metrics), ``final``,
    ``steps_done`` and ``train_its`` of a finished run; None when it has no final record."""
    records = read_metrics(run_dir)
    final = next((r for r in reversed(records) if r.get("final") and isinstance(r.get("eval"), dict)), None)
    if final is None:
        return None
    curve = [{"step": r["step"], "train_seconds": r["wall"], **flatten_eval(r["eval"])}
             for r in records if isinstance(r.get("eval"), dict)]
    logged = [r for r in records if "its" in r]
    last = logged[-1] if logged else None
    its = last["step"] / last["wall"] if last and last["wall"] > 0 else math.nan
    flat = flatten_eval(final["eval"])
    flat["train_seconds"] = final["wall"]  # over every attempt, not only the last one
    return {"curve": curve, "final": flat, "steps_done": final["step"], "train_its": its}


def recorded_argv(run_dir: Path) -> Optional[list[str]]:
    """The train arguments recorded in ``run.json`` (None if absent or unreadable)."""
    try:
        argv = json.loads((Path(run_dir) / "run.json").read_text()).get("argv")
    except (OSError, ValueError, AttributeError):
        return None
    return [str(a) for a in argv] if isinstance(argv, list) else None


def same_command(recorded: Optional[list[str]], identity: list[str]) -> bool:
    """Whether ``run.json``'s arguments are this job's (``identity`` starts with "train")."""
    if recorded is None:
        return True  # nothing to compare with: trust the directory name
    return strip_flags(recorded, {"--trainer.threads", "--trainer.resume"}) == identity[1:]


def run_state(run_dir: Path, identity: list[str]) -> tuple[str, Optional[int]]:
    """What a rerun does with a job's run directory:

    - ("new", None): no directory;
    - ("changed", None): made by another command (budget or flags changed);
    - ("finished", step): training and its final evaluation are done;
    - ("resume", step): interrupted; continue from the newest checkpoint (at ``step``);
    - ("partial", None): interrupted before its first checkpoint (start again).
    """
    run_dir = Path(run_dir)
    if not run_dir.exists():
        return "new", None
    if not same_command(recorded_argv(run_dir), identity):
        return "changed", None
    res = run_results(run_dir)
    if res is not None:
        return "finished", res["steps_done"]
    steps = checkpoint_steps(run_dir)
    if steps:
        return "resume", steps[-1]
    return "partial", None
