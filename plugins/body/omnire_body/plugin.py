"""Registers ``omnire bench humanpose`` (the human pose pipeline against ground truth)."""
from omnire.api import CommandSpec, hookimpl


def _bench_main(argv, plugins):
    from omnire_body.bench import main

    return main(argv, plugins)


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec("bench humanpose", "human pose sources (image estimator, LiDAR fitter, fusion) "
                                  "against a synthetic scene's true body poses: MPJPE, posed fraction (JSON + table)",
                                  _bench_main))
