"""Entry point (``omnire`` group, name ``export``): registers ``omnire export``."""
from omnire.api import CommandSpec, hookimpl


def _main(argv, plugins):
    from omnire_export.cli import main  # imported on use: listing commands stays cheap

    return main(argv, plugins)


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec("export", "a trained scene at a moment as standard 3DGS PLY files "
                                  "(whole, per node with poses, or a sequence) plus the sky map", _main))
