"""Entry point (``omnire`` group, name ``serve``): registers ``omnire serve`` and ``omnire bench serve``."""
from omnire.api import CommandSpec, hookimpl


def _serve(argv, plugins):
    from omnire_serve.cli import main

    return main(argv, plugins)


def _bench_serve(argv, plugins):
    from omnire_serve.bench import main

    return main(argv, plugins)


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec(
        "serve", "serve a trained scene over HTTP for closed-loop driving (neurad-studio's closed-loop API, "
                 "whole-rig renders, scenario edits, sessions)", _serve))
    registry.register(CommandSpec(
        "bench serve", "latency (p50, p95) of camera and rig renders through omnire serve, 1 and 4 clients",
        _bench_serve))
