"""omnire-sim: edit a reconstructed scene and render it (``omnire sim``), and ``omnire bench render``.

Python API: :class:`~omnire_sim.engine.Simulation` (a Reconstruction with a Scenario's edits,
renders any camera at any moment), the edit model in :mod:`omnire_sim.edits` and scenario
files in :mod:`omnire_sim.scenario`.
"""
from omnire_sim import edits
from omnire_sim.edits import *  # noqa: F403 - the edit model is part of this package's API
from omnire_sim.engine import Simulation
from omnire_sim.scenario import load_scenario, parse_scenario

__all__ = [*edits.__all__, "Simulation", "load_scenario", "parse_scenario"]
