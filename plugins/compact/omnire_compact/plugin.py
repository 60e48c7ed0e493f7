"""Entry point (``omnire`` group, name ``compact``): registers ``omnire compact`` (imported on use:
listing commands stays cheap)."""
from omnire.api import CommandSpec, lazy

SPECS = (CommandSpec("compact", "a smaller copy of a trained run: Gaussians pruned by their contribution to the "
                     "training views, optionally fine-tuned", lazy("omnire_compact.cli:main")),)
