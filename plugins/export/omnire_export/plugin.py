"""Entry point (``omnire`` group, name ``export``): registers ``omnire export`` (imported on use:
listing commands stays cheap)."""
from omnire.api import CommandSpec, lazy

SPECS = (CommandSpec("export", "a trained scene at a moment as standard 3DGS PLY files (whole, per node with "
                     "poses, or a sequence) plus the sky map", lazy("omnire_export.cli:main")),)
