"""Entry point (``omnire`` group, name ``batch``): registers the ``omnire batch`` command
(imported on use, so that listing commands does not import ray)."""
from omnire.api import CommandSpec, lazy

SPECS = (CommandSpec("batch", "many train+eval jobs (scenes x methods x variants x seeds) on Ray, locally or on a "
                     "cluster", lazy("omnire_batch.cli:main")),)
