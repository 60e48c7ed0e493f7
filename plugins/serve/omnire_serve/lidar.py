"""The LiDAR of ``omnire serve`` (``POST /render_lidar``, docs/closed_loop.md): the beam model
a request asks for, one revolution rendered from one sensor pose at one moment with the
session's edits, and its points encoded as npz or JSON.

A sweep is every ray of the beam model (beam-major: ray ``b * A + k`` is beam ``b`` at
azimuth ``k * 360 / A`` degrees in the sensor frame, x forward, y left, z up), all cast
from the request's pose at its timestamp (no rolling shutter: the request names one pose).
A ray gives a point when its rendered ray-drop probability is below 0.5; rays the model
drops are left out (``beam`` and ``column`` say which rays the points are). A run trained
without ``--method.lidar.enabled`` learned no intensity or ray drop: its sweep is geometry
only (a ray returns when the accumulated opacity reaches 0.5) and carries no intensity or
ray-drop fields; the response's ``meta.features`` says which are present.
"""
from __future__ import annotations

import dataclasses
import io
import json
import math
from typing import Optional

import numpy as np

from omnire.api import BeamModel, SceneDataError, beam_model_sweep, fixed_path, sweep_points
from omnire_serve.errors import RequestError

NPZ_MEDIA = "application/x-omnire-lidar+npz"
"""Content type of an npz sweep: numpy's ``.npz`` (``np.load``), one array per field plus
``meta`` (a JSON string)."""
FORMATS = ("npz", "json")
LEARNED = ("range", "intensity", "ray_drop")
GEOMETRY = ("range",)


def beam_model_from(value, default: Optional[BeamModel], max_rays: int, field: str = "beam_model") -> BeamModel:
    """The beam model of a request: ``value`` (``{"elevations_deg": [...], "azimuth_step_deg":
    x, "max_range": m, "min_range": m (default 0)}``) or, when absent (None), the scene's own
    ``default``; at most ``max_rays`` rays (beams x azimuth steps) a revolution."""
    if value is None:
        if default is None:
            raise RequestError(field, "this scene has no LiDAR beam model; send one: {\"elevations_deg\": [...], "
                                      "\"azimuth_step_deg\": degrees, \"max_range\": metres}")
        model = default
    else:
        if not isinstance(value, dict):
            raise RequestError(field, "expected an object {elevations_deg, azimuth_step_deg, max_range, min_range}")
        unknown = sorted(set(value) - {"elevations_deg", "azimuth_step_deg", "max_range", "min_range"})
        if unknown:
            raise RequestError(f"{field}.{unknown[0]}", "unknown field; expected elevations_deg, azimuth_step_deg, "
                                                      "max_range, min_range")
        elevations = value.get("elevations_deg")
        if not isinstance(elevations, list) or not elevations or not all(_number(e) for e in elevations):
            raise RequestError(f"{field}.elevations_deg", "expected a non-empty list of finite degrees")
        if len(elevations) > max_rays:
            raise RequestError(f"{field}.elevations_deg", f"{len(elevations)} beams: more than the limit of "
                                                          f"{max_rays} rays", 413)
        numbers = {}
        for key, default_value in (("azimuth_step_deg", None), ("max_range", None), ("min_range", 0.0)):
            v = value.get(key, default_value)
            if not _number(v):
                raise RequestError(f"{field}.{key}", f"{v!r}: expected a finite number")
            numbers[key] = float(v)
        if numbers["azimuth_step_deg"] <= 0:
            raise RequestError(f"{field}.azimuth_step_deg", f"{numbers['azimuth_step_deg']}: expected degrees > 0")
        rays = len(elevations) * round(360.0 / numbers["azimuth_step_deg"])
        if rays > max_rays:
            raise RequestError(field, f"{len(elevations)} beams x {round(360.0 / numbers['azimuth_step_deg'])} "
                                      f"azimuths = {rays} rays is more than the limit of {max_rays} "
                                      "(omnire serve --max-lidar-rays)", 413)
        try:
            model = BeamModel(np.asarray(elevations, dtype=np.float64), numbers["azimuth_step_deg"],
                              numbers["max_range"], numbers["min_range"], "request")
        except SceneDataError as exc:
            raise RequestError(field, str(exc).removeprefix("beam model 'request'").lstrip(".: ")) from None
    if model.num_beams * model.num_azimuths > max_rays:
        raise RequestError(field, f"the scene's beam model has {model.num_beams * model.num_azimuths} rays, more "
                                  f"than the limit of {max_rays} (omnire serve --max-lidar-rays); send a coarser one",
                           413)
    return model


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def beam_model_json(model: BeamModel) -> dict:
    """``model`` in the request's shape (``beam_model_from`` reads it back)."""
    return {"elevations_deg": np.round(model.elevations_deg, 6).tolist(),
            "azimuth_step_deg": 360.0 / model.num_azimuths, "max_range": float(model.max_range),
            "min_range": float(model.min_range)}


@dataclasses.dataclass(frozen=True)
class SweepPoints:
    """The P returning rays of a rendered revolution of ``model``.

    Attributes:
        x, y, z: (P,) float32 world metres.
        intensity, ray_drop: (P,) float32 in [0, 1]; None for a run that learned no LiDAR.
        beam: (P,) int16 beam index (row of ``model.elevations_deg``).
        column: (P,) int32 azimuth step (the ray's azimuth is ``column * 360 / A`` degrees).
        model: the beam model rendered.
        timestamp: microseconds.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    intensity: Optional[np.ndarray]
    ray_drop: Optional[np.ndarray]
    beam: np.ndarray
    column: np.ndarray
    model: BeamModel
    timestamp: int

    @property
    def features(self) -> tuple[str, ...]:
        return GEOMETRY if self.intensity is None else LEARNED

    def arrays(self) -> dict[str, np.ndarray]:
        names = ("x", "y", "z") + (() if self.intensity is None else ("intensity", "ray_drop")) + ("beam", "column")
        return {n: getattr(self, n) for n in names}

    def meta(self) -> dict:
        return {"timestamp": self.timestamp, "points": int(len(self.x)),
                "rays": self.model.num_beams * self.model.num_azimuths,
                "num_beams": self.model.num_beams, "num_azimuths": self.model.num_azimuths,
                "beam_model": beam_model_json(self.model), "features": list(self.features),
                "fields": list(self.arrays()), "frame": "world",
                "dropped": "left out (rays with ray-drop probability >= 0.5)" if self.intensity is not None
                else "left out (rays whose accumulated opacity stays below 0.5)"}



def range_image(points: dict[str, np.ndarray], sensor_to_world: np.ndarray, shape: tuple[int, int],
                max_range: float) -> np.ndarray:
    """(B, A) = ``shape`` float32 range image of a sweep's points (``x y z beam column``, (P,)
    each): the distance of each point from ``sensor_to_world``'s (4, 4) origin, at its beam
    row and azimuth column, at most ``max_range``; 0 where the ray returned nothing."""
    out = np.zeros(shape, np.float32)
    xyz = np.stack([points["x"], points["y"], points["z"]], -1).astype(np.float64)
    dist = np.linalg.norm(xyz - np.asarray(sensor_to_world, dtype=np.float64)[:3, 3], axis=1)
    out[points["beam"].astype(np.int64), points["column"].astype(np.int64)] = np.minimum(dist, max_range)
    return out


def render_points(recon, sensor_to_world: np.ndarray, time, seconds_on_clock: float, model: BeamModel,
                  edits, timestamp: int) -> SweepPoints:
    """One revolution of ``model`` from ``sensor_to_world`` (4, 4) at scene moment ``time``
    (``seconds_on_clock`` seconds on the log's clock), the scene drawn with ``edits``;
    geometry only when the run learned no LiDAR features."""
    import torch

    from omnire.api import LidarRays

    learned = recon.model.lidar_features is not None
    rays = LidarRays.from_beam_model(torch.as_tensor(sensor_to_world, dtype=torch.float32, device=recon.device),
                                     model)
    render = recon.render_lidar(rays, time, edits=edits, geometry_only=not learned)
    sweep = beam_model_sweep(model, seconds_on_clock)
    points = sweep_points(render, sweep, fixed_path(sensor_to_world), 1)
    kept = np.flatnonzero(render.ray_drop.detach().cpu().numpy() < 0.5)
    return SweepPoints(points["x"], points["y"], points["z"],
                       points["intensity"] if learned else None,
                       render.ray_drop.detach().cpu().numpy().astype(np.float32)[kept] if learned else None,
                       points["beam"], (kept % model.num_azimuths).astype(np.int32), model, timestamp)


def encode_points(points: SweepPoints, fmt: str) -> tuple[bytes, str]:
    """(body, content type): npz (:data:`NPZ_MEDIA`) or JSON ``{"meta": ..., "points":
    {field: [...]}}``."""
    if fmt == "json":
        body = {"meta": points.meta(), "points": {n: a.tolist() for n, a in points.arrays().items()}}
        return json.dumps(body).encode(), "application/json"
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(points.meta())), **points.arrays())
    return buf.getvalue(), NPZ_MEDIA


def decode_points(body: bytes, content_type: str) -> tuple[dict, dict[str, np.ndarray]]:
    """(meta, field -> (P,) array) of a /render_lidar response."""
    if content_type.startswith("application/json"):
        data = json.loads(body)
        dtypes = {"beam": np.int16, "column": np.int32}
        return data["meta"], {n: np.asarray(v, dtype=dtypes.get(n, np.float32)) for n, v in data["points"].items()}
    with np.load(io.BytesIO(body)) as z:
        return json.loads(str(z["meta"])), {n: z[n] for n in z.files if n != "meta"}
