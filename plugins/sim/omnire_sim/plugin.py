"""Entry point (``omnire`` group, name ``sim``): registers ``omnire sim`` and ``omnire bench render``."""
from omnire.api import CommandSpec, lazy

SPECS = (
    CommandSpec("sim", "render a trained scene with edits (remove / move / stop / insert actors, new pedestrian "
                "motions, new camera paths) to PNG frames and MP4 videos", lazy("omnire_sim.cli:main")),
    CommandSpec("bench render", "rendering speed (frames/s) and peak memory of trained runs at several resolutions",
                lazy("omnire_sim.bench:main")),
)
