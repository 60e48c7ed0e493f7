"""Entry point (``omnire`` group, name ``serve``): registers ``omnire serve`` and ``omnire bench serve``."""
from omnire.api import CommandSpec, lazy

SPECS = (
    CommandSpec("serve", "serve a trained scene over HTTP for closed-loop driving (neurad-studio's closed-loop API, "
                "whole-rig renders, scenario edits, sessions)", lazy("omnire_serve.cli:main")),
    CommandSpec("bench serve", "latency (p50, p95) of camera and rig renders through omnire serve, 1 and 4 clients",
                lazy("omnire_serve.bench:main")),
)
