"""Entry point (``omnire`` group, name ``compact``): registers ``omnire compact``."""
from omnire.api import CommandSpec, hookimpl


def _main(argv, plugins):
    from omnire_compact.cli import main  # imported on use: listing commands stays cheap

    return main(argv, plugins)


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec("compact", "a smaller copy of a trained run: Gaussians pruned by their "
                                  "contribution to the training views, optionally fine-tuned", _main))
