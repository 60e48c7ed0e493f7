"""What a rerun of a batch does with a job's run directory (``omnire train``'s, read through
:class:`omnire.rundir.RunDirectory`: its recorded arguments, metrics and checkpoints).

``omnire.rundir`` is imported directly rather than through ``omnire.api``: it needs neither
torch nor the rest of the core, so a Ray worker starts fast.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from omnire.rundir import RunDirectory
from omnire_batch.spec import strip_flags


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
    run = RunDirectory(run_dir)
    if not run.path.exists():
        return "new", None
    if not same_command(run.recorded_argv(), identity):
        return "changed", None
    res = run.results()
    if res is not None:
        return "finished", res["steps_done"]
    steps = run.checkpoint_steps()
    if steps:
        return "resume", steps[-1]
    return "partial", None
