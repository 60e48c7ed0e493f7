"""A rendered LiDAR sweep as the viewer draws it: one coloured point per return.

The points are ``omnire_sim.cli.sim_sweep``'s (the simulated scene at the viewer's moment:
the rays of the nearest recorded sweep from the recorded sensor path, the run's time
sectors), coloured by their rendered intensity or by their range from the sensor.
"""
from __future__ import annotations

from typing import Literal

import numpy as np

ColourBy = Literal["intensity", "range"]
COLOUR_BY: tuple[str, ...] = ("intensity", "range")
"""The panel's colour choices."""

RAMP = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64)
"""Colours (RGB, 0-255) at 0, 1/4, 1/2, 3/4 and 1 of the scale (the anchors of matplotlib's
viridis): dark for low values, yellow for high ones; linear in between."""


def ramp_colours(values: np.ndarray) -> np.ndarray:
    """``values`` (P,) in [0, 1] (clipped; NaN as 0) -> (P, 3) uint8 colours on :data:`RAMP`."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64)), 0.0, 1.0)
    anchors = np.linspace(0.0, 1.0, len(RAMP))
    rgb = np.stack([np.interp(v, anchors, RAMP[:, c]) for c in range(3)], axis=-1)
    return (rgb + 0.5).astype(np.uint8)


def point_colours(points: np.ndarray, sensor_positions: np.ndarray, by: ColourBy) -> tuple[np.ndarray, str]:
    """(P, 3) uint8 colours of a sweep's points (structured, ``omnire.api.POINT_FIELDS``) and
    a caption naming the scale. ``sensor_positions`` (P, 3): where the sensor was when each
    point's ray fired. Intensity is on its own [0, 1] scale; range runs from 0 to the 99th
    percentile of the sweep's ranges (farther points saturate)."""
    if by == "intensity":
        return ramp_colours(points["intensity"]), "intensity 0 (dark) to 1 (yellow)"
    if by != "range":
        raise ValueError(f"colour by {by!r}: expected one of {COLOUR_BY}")
    xyz = np.stack([points["x"], points["y"], points["z"]], axis=-1).astype(np.float64)
    rng = np.linalg.norm(xyz - sensor_positions, axis=-1)
    top = float(np.percentile(rng, 99)) if len(rng) else 1.0
    return ramp_colours(rng / max(top, 1e-6)), f"range 0 (dark) to {top:.1f} m (yellow)"
