"""Entry point (``omnire`` group, name ``batch``): registers the ``omnire batch`` command."""
from omnire.api import CommandSpec, hookimpl


def _main(argv, plugins):
    # Imported on use so that listing commands does not import ray.
    from omnire_batch.cli import main

    return main(argv, plugins)


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec(
        "batch", "many train+eval jobs (scenes x methods x variants x seeds) on Ray, locally or on a cluster", _main))
