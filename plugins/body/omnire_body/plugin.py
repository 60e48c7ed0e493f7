"""Registers ``omnire bench humanpose`` (the human pose pipeline against ground truth)."""
from omnire.api import CommandSpec, lazy

SPECS = (CommandSpec("bench humanpose", "human pose sources (image estimator, LiDAR fitter, fusion) against a "
                     "synthetic scene's true body poses: MPJPE, posed fraction (JSON + table)",
                     lazy("omnire_body.bench:main")),)
