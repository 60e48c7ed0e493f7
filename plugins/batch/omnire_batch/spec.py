"""The jobs of a batch as plain data: what a Ray worker unpickles and runs.

Kept free of torch and of the omnire core (nothing here imports them), so that a Ray worker
starts fast; the ``omnire train`` subprocess is what loads them.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional


@dataclasses.dataclass(frozen=True)
class Scene:
    name: str
    dataparser: str
    data: Path
    """Absolute path (workers must see it at this path)."""
    args: tuple[str, ...] = ()
    """Dataparser flags."""
    synth: Optional[str] = None
    """Preset generated into ``data`` (once, before its jobs) when it holds no scene."""
    synth_args: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class MethodEntry:
    label: str
    method: str
    flags: tuple[str, ...] = ()
    num_cpus: Optional[float] = None
    num_gpus: Optional[float] = None
    memory_gb: Optional[float] = None
    threads: Optional[int] = None


@dataclasses.dataclass(frozen=True)
class Variant:
    name: str
    flags: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class Job:
    """One ``omnire train`` run (its final evaluation included) in its own run directory."""

    scene: Scene
    method: MethodEntry
    variant: Variant
    seed: int
    steps: int
    seconds: float
    eval_every: int
    checkpoint_every: int
    common_flags: tuple[str, ...]
    num_cpus: float
    num_gpus: float
    memory_gb: float
    threads: int
    timeout: float
    output: Path

    @property
    def label(self) -> str:
        return self.method.label + (f"+{self.variant.name}" if self.variant.name else "")

    @property
    def name(self) -> str:
        return f"{self.label}-seed{self.seed}"

    @property
    def key(self) -> str:
        return f"{self.scene.name}/{self.name}"

    @property
    def flags(self) -> list[str]:
        """Method and variant flags (what distinguishes this row from the plain method)."""
        return [*self.method.flags, *self.variant.flags]

    @property
    def run_dir(self) -> Path:
        return self.output / "runs" / self.scene.name / self.name

    @property
    def log_path(self) -> Path:
        return self.output / "logs" / self.scene.name / f"{self.name}.log"

    @property
    def record_path(self) -> Path:
        return self.output / "jobs" / self.scene.name / f"{self.name}.json"

    def train_args(self) -> list[str]:
        """``omnire train ...`` arguments (after ``omnire``), without --trainer.resume."""
        args = ["train", self.method.method, self.scene.dataparser, "--data", str(self.scene.data), *self.scene.args,
                *self.common_flags, *self.flags,
                "--trainer.max-steps", str(self.steps), "--trainer.max-seconds", str(self.seconds),
                "--trainer.eval-every", str(self.eval_every), "--trainer.checkpoint-every", str(self.checkpoint_every),
                "--trainer.seed", str(self.seed), "--trainer.output-dir", str(self.run_dir.parent),
                "--trainer.run-name", self.name, "--trainer.no-progress", "--trainer.threads", str(self.threads)]
        every = [*self.common_flags, *self.flags]
        if self.num_gpus > 0 and not any(a.startswith("--trainer.device") for a in every):
            args += ["--trainer.device", "cuda"]
        return args

    def identity(self) -> list[str]:
        """What makes two runs the same job: the train arguments less the thread count."""
        return strip_flags(self.train_args(), {"--trainer.threads", "--trainer.resume"})


def strip_flags(argv: list[str], names: set[str]) -> list[str]:
    """``argv`` without the given ``--flag VALUE`` / ``--flag=VALUE`` pairs."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in names:
            skip = True
            continue
        if a.split("=", 1)[0] in names and "=" in a:
            continue
        out.append(a)
    return out
