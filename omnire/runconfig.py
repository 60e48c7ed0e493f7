"""What ``omnire train <method> <dataparser> [flags]`` builds: the command line, parsed into a
:class:`TrainConfig` with tyro from the registries at call time, validated before any work.

A run directory records the exact arguments (``run.json``), so eval, render and the scene
runtime rebuild the same configuration by parsing them again.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional, Union

import tyro

from omnire.errors import ConfigError
from omnire.method import MethodConfig
from omnire.registry import RegistryError

if TYPE_CHECKING:
    import torch


@dataclasses.dataclass
class TrainerConfig:
    """Loop, logging, evaluation and checkpoint settings."""

    max_steps: Optional[int] = None
    """Training steps (one image per step): the step budget, which the schedules (learning-rate
    decay, densification, SH bands, coarse-to-fine, node warm-ups) span. Not given: 3000, or
    with --trainer.max-seconds no step limit (see omnire/schedule.py)."""
    max_seconds: float = 0.0
    """Time budget: seconds of training (evaluation and checkpoints excluded), over which the
    schedules are laid (the larger of step / max-steps and seconds / max-seconds is the
    run's progress); training ends when either budget is spent. 0: no time budget, the
    schedules follow the step count exactly. A time budget is not bit-reproducible: see
    omnire/schedule.py."""
    eval_every: int = 0
    """Evaluate on the held-out frames every N steps (0: only at the end)."""
    log_every: int = 25
    """Write training metrics every N steps."""
    checkpoint_every: int = 1000
    """Save a checkpoint every N steps (and always at the end)."""
    output_dir: Path = Path("outputs")
    """Where run directories are created."""
    run_name: Optional[str] = None
    """Run directory name (default: <scene>-<method>-<time>). An existing run directory is
    refused unless --trainer.resume names it."""
    seed: int = 0
    """Seed for initialisation, view sampling and densification."""
    threads: int = 0
    """torch CPU threads (0: torch's default)."""
    retain_freed_memory: bool = True
    """Keep memory freed between steps in the process instead of returning it to the OS
    (glibc only; see omnire/allocator.py): a step stops page-faulting its large tensors back
    in (about 10% of a step here). The process does not shrink between steps; see the module
    for the cost in peak memory."""
    device: str = "cpu"
    """Torch device (cpu or cuda)."""
    resume: Optional[Path] = None
    """Continue a run: its directory (the newest intact checkpoint) or a checkpoint file.
    Training continues in that run directory; the method and data selection must be the
    recorded ones."""
    eval_train_views: int = 24
    """Training views evaluated for the reconstruction metrics (evenly spaced; 0 = all)."""
    progress: bool = True
    """Show the rich progress bar."""
    observers: tuple[str, ...] = ()
    """Training observers to run, registered by plugins (``omnire plugins`` lists them; e.g.
    viewer: the scene live in the browser). Each also answers to ``--<name>`` (``--viewer``)."""
    observe_every: int = 100
    """Steps between observer updates."""
    observer_options: tuple[str, ...] = ()
    """key=value options passed to the observers (e.g. for the viewer: host=0.0.0.0 port=8081)."""

    def __post_init__(self) -> None:
        validate_trainer_config(self)


def validate_trainer_config(tc: TrainerConfig) -> None:
    """Reject values that cannot work, naming the flag (before any work is done)."""
    positive = {"max_steps": tc.max_steps, "log_every": tc.log_every, "checkpoint_every": tc.checkpoint_every,
                "observe_every": tc.observe_every}
    for name, value in positive.items():
        if value is not None and value <= 0:
            raise ConfigError(f"--trainer.{name.replace('_', '-')} {value}: must be a positive number of steps")
    for name, value in {"max_seconds": tc.max_seconds, "eval_every": tc.eval_every, "threads": tc.threads,
                        "eval_train_views": tc.eval_train_views}.items():
        if value < 0 or value != value or value == float("inf"):
            raise ConfigError(f"--trainer.{name.replace('_', '-')} {value}: must be a finite number >= 0 (0: "
                              + {"max_seconds": "no time limit", "eval_every": "only at the end",
                                 "threads": "torch's default", "eval_train_views": "all"}[name] + ")")
    parse_device(tc.device, "--trainer.device")
    for option in tc.observer_options:
        if "=" not in option or not option.split("=", 1)[0].strip():
            raise ConfigError(f"--trainer.observer-options {option!r}: expected key=value")
    if tc.run_name is not None and (not tc.run_name.strip() or "/" in tc.run_name or tc.run_name in (".", "..")):
        raise ConfigError(f"--trainer.run-name {tc.run_name!r}: must be a plain directory name")


@dataclasses.dataclass
class TrainConfig:
    """What ``omnire train <method> <dataparser>`` builds."""

    method_name: str
    dataparser_name: str
    method: MethodConfig
    dataparser: Any
    trainer: TrainerConfig


def _subcommand_union(types: list):
    # A Union needs two members; a suppressed None keeps a single entry a subcommand.
    return Union[tuple(types) + (Annotated[None, tyro.conf.Suppress],)]


def train_cli_type(plugins):
    """Union over methods of dataclasses (dataparser subcommand, method, trainer), built
    from the registries at call time. A method or dataparser whose factory raises is
    reported as a plugin failure and left out (it cannot stop runs that do not use it)."""
    dp_types = []
    for spec in plugins.dataparsers:
        default = plugins.call(plugins.dataparsers, spec.name, "dataparser config factory", spec.config_factory)
        if default is None:
            continue
        dp_types.append(Annotated[type(default), tyro.conf.subcommand(spec.name, default=default,
                                                                       description=spec.description)])
    if not dp_types:
        raise RegistryError("no dataparser is installed (e.g. pip install -e dataparsers/pandaset)")
    dp_union = _subcommand_union(dp_types)
    method_types = []
    for spec in plugins.methods:
        default = plugins.call(plugins.methods, spec.name, "method factory", spec.config_factory)
        if default is None:
            continue
        cls = dataclasses.make_dataclass(
            f"Train_{spec.name}",
            [
                ("dataparser", tyro.conf.OmitArgPrefixes[dp_union]),
                ("method", type(default), dataclasses.field(default_factory=spec.config_factory)),
                ("trainer", TrainerConfig, dataclasses.field(default_factory=TrainerConfig)),
            ],
        )
        cls._method_name = spec.name
        method_types.append(Annotated[cls, tyro.conf.subcommand(spec.name, description=spec.description)])
    if not method_types:
        raise RegistryError("no method is registered")
    return _subcommand_union(method_types)


def expand_observer_flags(argv: list[str], observer_names: list[str]) -> list[str]:
    """``--<observer>`` (e.g. ``--viewer``) is short for ``--trainer.observers <observer>``;
    several, and an explicit ``--trainer.observers`` list, are merged into one list."""
    flags = {f"--{name}": name for name in observer_names}
    wanted = [flags[a] for a in argv if a in flags]
    if not wanted:
        return list(argv)
    out = [a for a in argv if a not in flags]
    if "--trainer.observers" in out:
        i = out.index("--trainer.observers") + 1
        listed = []
        while i < len(out) and not out[i].startswith("--"):
            listed.append(out[i])
            i += 1
        extra = [n for n in dict.fromkeys(wanted) if n not in listed]
        return out[:i] + extra + out[i:]
    return out + ["--trainer.observers", *dict.fromkeys(wanted)]


def parse_train_args(argv: list[str], plugins) -> TrainConfig:
    """``argv`` of ``omnire train`` (without the command) -> a validated :class:`TrainConfig`."""
    argv = expand_observer_flags(argv, plugins.train_observers.names())
    parsed = tyro.cli(
        train_cli_type(plugins), args=argv, prog="omnire train",
        config=(tyro.conf.OmitSubcommandPrefixes, tyro.conf.CascadeSubcommandArgs, tyro.conf.SuppressFixed),
    )
    dp_name = next(s.name for s in plugins.dataparsers
                   if type(plugins.call(plugins.dataparsers, s.name, "dataparser config factory", s.config_factory))
                   is type(parsed.dataparser))
    return TrainConfig(type(parsed)._method_name, dp_name, parsed.method, parsed.dataparser, parsed.trainer)


def path_fields(config: Any) -> list[Path]:
    """Every :class:`~pathlib.Path` value in a (nested) config of dataclasses, dicts, lists."""
    out: list[Path] = []
    if isinstance(config, Path):
        out.append(config)
    elif dataclasses.is_dataclass(config) and not isinstance(config, type):
        for f in dataclasses.fields(config):
            out += path_fields(getattr(config, f.name))
    elif isinstance(config, dict):
        for v in config.values():
            out += path_fields(v)
    elif isinstance(config, (list, tuple)):
        for v in config:
            out += path_fields(v)
    return out


def absolute_argv(argv: list[str], config: TrainConfig, cwd: Path) -> list[str]:
    """``argv`` with every relative path value of ``config`` made absolute (against
    ``cwd``), so a recorded command line means the same from any directory. Only tokens
    that are exactly a path value of the parsed config are rewritten."""
    relative = {str(p): str((cwd / p).resolve()) for p in path_fields(config) if not p.is_absolute()}
    out = []
    for token in argv:
        if token.startswith("--") and "=" in token:
            flag, value = token.split("=", 1)
            out.append(f"{flag}={relative.get(value, value)}")
        else:
            out.append(relative.get(token, token))
    return out


def parse_device(value: str, flag: str = "--device") -> torch.device:
    """``value`` as a torch device this build can use (cpu, or cuda[:N] where CUDA is
    available); a :class:`ConfigError` naming ``flag`` otherwise."""
    import torch

    try:
        device = torch.device(value)
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(f"{flag} {value!r}: not a torch device ({exc}); expected cpu or cuda[:N]") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{flag} {value}: this torch build has no usable CUDA device "
                          f"(torch {torch.__version__}); use {flag} cpu")
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"{flag} {value}: only cpu and cuda are supported")
    return device
