"""Run directories: what a training run leaves behind, and reading it back safely.

Layout::

    run.json              the exact (path-absolute) command line, method, dataparser, node assignment
    metrics.jsonl         one JSON object per logged step / evaluation
    train.log             the run's log (per-actor initialisation details, warnings)
    checkpoints/step-NNNNNN.pt   model, optimiser, densification and RNG state (atomic writes)
    eval/step-NNNNNN.json

Two runs never share a directory: creating one that holds a run is refused unless the run
is resumed. Checkpoints are chosen by step number; a damaged newest checkpoint is reported
and the newest intact one used instead.
"""
from __future__ import annotations

import dataclasses
import json
import os
import pickle
import re
import warnings
from pathlib import Path
from typing import Any, Optional

from omnire.errors import UserError

CHECKPOINT_PATTERN = re.compile(r"^step-(\d+)\.pt$")


class RunDirectoryError(UserError):
    """A run directory or one of its files is missing, malformed or refused (message names the file)."""


class CheckpointError(RunDirectoryError):
    """A checkpoint file cannot be used (damaged, empty, not a checkpoint, or unsafe)."""


@dataclasses.dataclass
class RunInfo:
    """The contents of ``run.json``."""

    argv: list[str]
    """The ``omnire train`` arguments (after the command), paths absolute."""
    method: str
    dataparser: str
    node_assignment: dict[str, list[str]]
    """Track ids per node type, as assigned when the run started."""
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Everything else recorded (rasterizer, scene name, attribution, plugin versions, cwd)."""

    REQUIRED = {"argv": list, "method": str, "dataparser": str, "node_assignment": dict}

    @classmethod
    def parse(cls, path: Path) -> "RunInfo":
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise RunDirectoryError(f"{path.parent}: not a run directory (no run.json)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise RunDirectoryError(f"{path}: not readable JSON ({exc})") from None
        if not isinstance(data, dict):
            raise RunDirectoryError(f"{path}: expected a JSON object, got {type(data).__name__}")
        for key, kind in cls.REQUIRED.items():
            if key not in data:
                raise RunDirectoryError(f"{path}: field {key!r} is missing")
            if not isinstance(data[key], kind):
                raise RunDirectoryError(f"{path}: field {key!r} must be a {kind.__name__}, "
                                        f"got {type(data[key]).__name__}")
        if not all(isinstance(a, str) for a in data["argv"]):
            raise RunDirectoryError(f"{path}: field 'argv' must be a list of strings")
        assignment = data["node_assignment"]
        if not all(isinstance(v, list) and all(isinstance(i, str) for i in v) for v in assignment.values()):
            raise RunDirectoryError(f"{path}: field 'node_assignment' must map node types to lists of track ids")
        extra = {k: v for k, v in data.items() if k not in cls.REQUIRED}
        return cls(data["argv"], data["method"], data["dataparser"], assignment, extra)

    def to_json(self) -> str:
        return json.dumps({"argv": self.argv, "method": self.method, "dataparser": self.dataparser,
                           "node_assignment": self.node_assignment, **self.extra}, indent=2)


class RunDirectory:
    """One run's directory (absolute path)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path).resolve()
        self.info_path = self.path / "run.json"
        self.metrics_path = self.path / "metrics.jsonl"
        self.log_path = self.path / "train.log"
        self.checkpoint_dir = self.path / "checkpoints"

    def holds_run(self) -> bool:
        return self.info_path.exists()

    def create(self) -> None:
        """Create the directory for a new run; refuse one that already holds a run."""
        if self.holds_run():
            raise RunDirectoryError(
                f"{self.path}: already holds a run; choose another --trainer.run-name, or continue it with "
                f"--trainer.resume {self.path}")
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunDirectoryError(f"{self.path}: cannot create the run directory ({exc.strerror or exc})") from None

    def read_info(self) -> RunInfo:
        return RunInfo.parse(self.info_path)

    def checkpoint_path(self, step: int) -> Path:
        return self.checkpoint_dir / f"step-{step:06d}.pt"

    def checkpoints(self) -> list[tuple[int, Path]]:
        """(step, path) of every checkpoint file, by step number."""
        if not self.checkpoint_dir.is_dir():
            return []
        found = []
        for p in self.checkpoint_dir.iterdir():
            m = CHECKPOINT_PATTERN.match(p.name)
            if m and p.is_file():
                found.append((int(m.group(1)), p))
        return sorted(found)

    def checkpoint_steps(self) -> list[int]:
        """Steps of the checkpoint files, ascending."""
        return [step for step, _ in self.checkpoints()]

    def recorded_argv(self) -> Optional[list[str]]:
        """The train arguments recorded in ``run.json``, or None when it is absent or unreadable
        (for callers that only compare; :meth:`read_info` reports what is wrong)."""
        try:
            argv = json.loads(self.info_path.read_text(encoding="utf-8")).get("argv")
        except (OSError, ValueError, AttributeError):
            return None
        return [str(a) for a in argv] if isinstance(argv, list) else None

    def data_path(self) -> Optional[Path]:
        """The dataset directory the run was trained on (``--data`` of the recorded command;
        None when not recorded)."""
        argv = self.recorded_argv() or []
        for i, a in enumerate(argv):
            if a == "--data" and i + 1 < len(argv):
                return Path(argv[i + 1])
            if a.startswith("--data="):
                return Path(a.split("=", 1)[1])
        return None

    def read_metrics(self) -> list[dict]:
        """The records of ``metrics.jsonl`` as one uninterrupted run would have written them.

        A resumed run continues from its checkpoint: records past the checkpoint's step that an
        interrupted attempt left are dropped where the steps go back, and training wall time,
        which a resumed trainer may restart from zero, is offset so that it keeps growing across
        attempts (by the time of the last kept record, i.e. exact when checkpoints fall on
        logged steps). Unparsable lines (a write cut by a kill) are skipped.
        """
        if not self.metrics_path.is_file():
            return []
        out: list[dict] = []
        offset = 0.0
        for line in self.metrics_path.read_text(errors="replace").splitlines():
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

    def results(self) -> Optional[dict]:
        """A finished run's results in ``omnire bench train``'s form: ``curve`` (one entry per
        evaluation: step, train_seconds and the :func:`flatten_eval` metrics), ``final``,
        ``steps_done`` and ``train_its``; None when it has no final evaluation."""
        records = self.read_metrics()
        final = next((r for r in reversed(records) if r.get("final") and isinstance(r.get("eval"), dict)), None)
        if final is None:
            return None
        curve = [{"step": r["step"], "train_seconds": r["wall"], **flatten_eval(r["eval"])}
                 for r in records if isinstance(r.get("eval"), dict)]
        logged = [r for r in records if "its" in r]
        last = logged[-1] if logged else None
        its = last["step"] / last["wall"] if last and last["wall"] > 0 else float("nan")
        flat = flatten_eval(final["eval"])
        flat["train_seconds"] = final["wall"]  # over every attempt, not only the last one
        return {"curve": curve, "final": flat, "steps_done": final["step"], "train_its": its}

    def remove_temporary_files(self) -> list[Path]:
        """Delete leftovers of interrupted atomic writes (``.step-*.pt.*.tmp``)."""
        removed = []
        if self.checkpoint_dir.is_dir():
            for p in self.checkpoint_dir.glob(".*.tmp"):
                p.unlink(missing_ok=True)
                removed.append(p)
        return removed

    def load_latest_checkpoint(self, map_location: Any = "cpu", mmap: bool = False) -> tuple[Path, dict]:
        """The newest intact checkpoint (by step number) and its state. Damaged ones are
        skipped with a warning naming them. ``mmap``: see :func:`load_checkpoint`."""
        ckpts = self.checkpoints()
        if not ckpts:
            raise RunDirectoryError(f"{self.path}: no checkpoints/step-*.pt inside (the run saved no checkpoint)")
        problems = []
        for _, path in reversed(ckpts):
            try:
                return path, load_checkpoint(path, map_location, mmap)
            except CheckpointError as exc:
                problems.append(str(exc))
                warnings.warn(f"{exc}; trying an older checkpoint", stacklevel=2)
        raise RunDirectoryError(f"{self.path}: no intact checkpoint: " + "; ".join(problems))

    def truncate_metrics(self, step: int) -> None:
        """Drop metric records after ``step`` (a resumed run repeats those steps)."""
        if not self.metrics_path.is_file():
            return
        from omnire.io.atomic import atomic_write_text

        kept = []
        for line in self.metrics_path.read_text().splitlines():
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut by an interruption
            if isinstance(record, dict) and int(record.get("step", 0)) <= step and not record.get("final"):
                kept.append(line)
        atomic_write_text(self.metrics_path, "".join(k + "\n" for k in kept))


def flatten_eval(ev: dict) -> dict:
    """An evaluation record -> one flat dict: top-level numbers plus ``reconstruction.*``,
    ``novel_view.*`` and ``lidar.*`` (the keys the benchmark tables and plots read), and each
    LiDAR baseline's figures as ``lidar_baselines.<baseline>.*``."""
    flat = {k: v for k, v in ev.items() if not isinstance(v, dict)}
    for split in ("reconstruction", "novel_view", "lidar"):
        for k, v in (ev.get(split) or {}).items():
            if not isinstance(v, dict):
                flat[f"{split}.{k}"] = v
    for name, figures in (ev.get("lidar_baselines") or {}).items():
        for k, v in figures.items():
            flat[f"lidar_baselines.{name}.{k}"] = v
    return flat


CHECKPOINT_KEYS = ("step", "model")


def load_checkpoint(path: Path, map_location: Any = "cpu", mmap: bool = False) -> dict:
    """A checkpoint's state dict, loaded with ``weights_only=True`` (tensors and plain data
    only). With ``mmap`` (CPU only) the tensors are memory-mapped from the file and read on
    first use (the optimiser state of a checkpoint then costs nothing unless touched).
    Raises :class:`CheckpointError` naming the file when it is empty, truncated, not a
    checkpoint, or holds anything else (refused as unsafe)."""
    import torch

    path = Path(path)
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read checkpoint ({exc.strerror or exc})") from None
    if size == 0:
        raise CheckpointError(f"{path}: empty checkpoint file")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except pickle.UnpicklingError:
        raise CheckpointError(f"{path}: refused as unsafe (it holds objects other than tensors and plain data); "
                              "it was not written by omnire") from None
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged zip
        raise CheckpointError(f"{path}: damaged or truncated checkpoint ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else 'unreadable'})") from None
    if not isinstance(state, dict) or any(k not in state for k in CHECKPOINT_KEYS):
        raise CheckpointError(f"{path}: not an omnire checkpoint (expected a dict with {list(CHECKPOINT_KEYS)})")
    return state


def find_checkpoint(path: Path, map_location: Any = "cpu", mmap: bool = False) -> tuple[RunDirectory, Path, dict]:
    """A run directory or a checkpoint file inside one -> (run directory, checkpoint path,
    state). For a directory, the newest intact checkpoint."""
    path = Path(path)
    if path.is_file():
        run = RunDirectory(path.parent.parent if path.parent.name == "checkpoints" else path.parent)
        return run, path, load_checkpoint(path, map_location, mmap)
    if not path.is_dir():
        raise RunDirectoryError(f"{path}: no such run directory or checkpoint file")
    run = RunDirectory(path)
    ckpt, state = run.load_latest_checkpoint(map_location, mmap)
    return run, ckpt, state


def step_of(path: Optional[Path]) -> Optional[int]:
    m = CHECKPOINT_PATTERN.match(path.name) if path is not None else None
    return int(m.group(1)) if m else None
