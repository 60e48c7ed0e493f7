"""Entry point (``omnire`` group, name ``sim``): registers ``omnire sim`` and ``omnire bench render``."""
from omnire.api import CommandSpec, hookimpl


def _sim(argv, plugins):
    from omnire_sim.cli import main

    return main(argv, plugins)


def _bench_render(argv, plugins):
    from omnire_sim.bench import main

    return main(argv, plugins)


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec(
        "sim", "render a trained scene with edits (remove / move / stop / insert actors, new pedestrian motions, "
               "new camera paths) to PNG frames and MP4 videos", _sim))
    registry.register(CommandSpec(
        "bench render", "rendering speed (frames/s) and peak memory of trained runs at several resolutions",
        _bench_render))
