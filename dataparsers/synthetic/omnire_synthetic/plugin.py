"""omnire plugin: the ``synthetic`` dataparser and the ``omnire synth`` command."""
from __future__ import annotations

from omnire.api import CommandSpec, DataparserSpec, hookimpl


def _config():
    from omnire_synthetic.dataparser import SyntheticDataparserConfig

    return SyntheticDataparserConfig()


def _synth_main(argv: list[str], plugins) -> int:
    from omnire_synthetic.cli import main

    return main(argv, plugins)


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    registry.register(
        DataparserSpec(
            "synthetic",
            "Synthetic street scene with ground truth: generated into --data if it is not there yet, "
            "then read with the processed-scene reader",
            _config,
        )
    )


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec("synth", "Generate a synthetic driving scene with ground truth", _synth_main))
