"""omnire-sim: edit a reconstructed scene and render it (``omnire sim``), and ``omnire bench render``.

Python API: :class:`~omnire_sim.engine.Simulation` (a Reconstruction with a Scenario's edits,
renders any camera at any moment), the edit model in :mod:`omnire_sim.edits` and scenario
files in :mod:`omnire_sim.scenario`.
"""
from omnire_sim.edits import (
    ActorEdit,
    CameraSpec,
    Clock,
    Insertion,
    LaneShift,
    Motion,
    OutputSpec,
    Placement,
    Scenario,
    ScenarioError,
    Trajectory,
    Waypoint,
)
from omnire_sim.engine import Simulation
from omnire_sim.scenario import load_scenario, parse_scenario

__all__ = [
    "ActorEdit", "CameraSpec", "Clock", "Insertion", "LaneShift", "Motion", "OutputSpec", "Placement", "Scenario",
    "ScenarioError", "Simulation", "Trajectory", "Waypoint", "load_scenario", "parse_scenario",
]
