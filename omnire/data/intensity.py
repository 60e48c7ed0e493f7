"""LiDAR return intensity: the scale a dataset's files store it on, and its map to [0, 1],
the scale :class:`~omnire.data.scene.LidarSweeps` carries and LiDAR learning predicts (a
sigmoid, omnire/lidarmodel.py). Every reader converts through one of these scales, so a file
whose values leave its documented range is refused with the file, field and range named,
never clipped (docs/lidar.md, "Intensity scales").
"""
from __future__ import annotations

import dataclasses

import numpy as np

from omnire.data.scene import SceneDataError


@dataclasses.dataclass(frozen=True)
class IntensityScale:
    """How a file stores intensity. ``full_scale`` > 0: numbers in 0..full_scale, divided by
    it; None: finite numbers >= 0 without a documented top (Waymo), mapped by tanh, which
    keeps small values nearly as they are (tanh(x) ~ x below about 0.3) and squeezes the rare
    retro-reflector returns far above 1 under 1 without a cut."""

    name: str
    full_scale: float | None

    @property
    def expected(self) -> str:
        """The values a file on this scale may hold, for error messages."""
        if self.full_scale is None:
            return "finite numbers >= 0"
        return f"numbers in 0..{self.full_scale:g}"

    def to_unit(self, values: np.ndarray, field: str, error: type[SceneDataError] = SceneDataError) -> np.ndarray:
        """File values (N,) -> (N,) float32 in [0, 1].

        Raises ``error`` "<field> must hold <expected> (found <value>, <k> of <N> values)"
        when a value is NaN, inf, negative or above the full scale; ``field`` names the file
        and its column (e.g. ``"lidar/003.bin: column 4 (intensity)"``)."""
        v = np.asarray(values, dtype=np.float64)
        top = np.inf if self.full_scale is None else self.full_scale
        bad = ~((v >= 0) & (v <= top) & np.isfinite(v))
        if bad.any():
            raise error(f"{field} must hold {self.expected} (found {v[bad][0]:g}, {int(bad.sum())} of {v.size} "
                        f"values; {self.name} scale)")
        unit = np.tanh(v) if self.full_scale is None else v / self.full_scale
        return unit.astype(np.float32)

    def from_unit(self, unit: np.ndarray) -> np.ndarray:
        """(N,) intensity in [0, 1] ([0, 1) on the unbounded scale) -> (N,) float64 file values,
        the inverse of :meth:`to_unit` (writers of a dataset's files)."""
        u = np.asarray(unit, dtype=np.float64)
        top = 1.0 if self.full_scale is not None else np.nextafter(1.0, 0.0)
        if u.size and not (u.min() >= 0 and u.max() <= top):
            raise ValueError(f"intensity in [0, 1{']' if self.full_scale is not None else ')'} expected, "
                             f"got {u.min():g}..{u.max():g}")
        return np.arctanh(u) if self.full_scale is None else u * self.full_scale


BYTE_INTENSITY = IntensityScale("0-255", 255.0)
"""Whole-byte intensity 0..255: PandaSet ``i``, nuScenes ``.pcd.bin`` column 4, Argoverse 2
``intensity`` (uint8), nuPlan's merged ``.pcd`` clouds (Hesai Pandar returns)."""

UNIT_INTENSITY = IntensityScale("0-1", 1.0)
"""Reflectance already in 0..1: KITTI's Velodyne ``.bin`` column 4."""

UNBOUNDED_INTENSITY = IntensityScale("unbounded", None)
"""Waymo's range image channel 1: non-negative, no documented top (mostly below 1)."""
