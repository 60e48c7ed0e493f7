"""How the environment reaches the scene: in the same process (:class:`LocalTransport`,
an :class:`~omnire_serve.served.Episode` of a ServedScene) or through ``omnire serve``
(:class:`HttpTransport`, an :class:`~omnire_serve.client.OmnireClient`). Both offer the same
six calls with the same values, so the environment does not know which it has."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from omnire_serve.client import OmnireClient
from omnire_serve.served import Episode, ServedScene


class _SessionTransport:
    """What both transports do alike: ``session`` (an Episode or a client of one) takes the
    reset and the scenario edits."""

    def __init__(self, session: "Episode | OmnireClient") -> None:
        self.session = session

    def reset(self, scenario: Optional[dict]) -> None:
        self.session.reset()
        if scenario:
            self.session.set_scenario(scenario)


class LocalTransport(_SessionTransport):
    """The scene in this process."""

    def __init__(self, served: ServedScene) -> None:
        super().__init__(Episode(served))
        self.served = served

    def metadata(self) -> dict:
        return self.served.metadata()

    def render_rig(self, rig_to_world: np.ndarray, timestamp: int, cameras: Sequence[str],
                   size: Optional[tuple[int, int]]) -> dict[str, np.ndarray]:
        s = self.served
        pose = s.pose(rig_to_world, "pose")
        cams = [s.camera_index(n, "cameras") for n in cameras]
        sizes = [s.size_of(*(size or (None, None)), c) for c in cams]
        return self.session.render_rig(pose, s.seconds_at(timestamp), cams, sizes)

    def render_lidar(self, sensor_to_world: np.ndarray, timestamp: int, beam_model: Optional[dict]
                     ) -> tuple[dict, dict[str, np.ndarray]]:
        s = self.served
        points = self.session.render_lidar(s.pose(sensor_to_world, "pose"), s.seconds_at(timestamp),
                                           s.beam_model(beam_model))
        return points.meta(), points.arrays()

    def actors_at(self, timestamp: int) -> list[dict]:
        return [b.as_json() for b in self.session.boxes_at(self.served.seconds_at(timestamp))]


class HttpTransport(_SessionTransport):
    """The scene behind an ``omnire serve`` server."""

    def metadata(self) -> dict:
        return self.session.metadata()

    def render_rig(self, rig_to_world: np.ndarray, timestamp: int, cameras: Sequence[str],
                   size: Optional[tuple[int, int]]) -> dict[str, np.ndarray]:
        return self.session.render_rig(rig_to_world, timestamp, cameras, size, image_format="raw")

    def render_lidar(self, sensor_to_world: np.ndarray, timestamp: int, beam_model: Optional[dict]
                     ) -> tuple[dict, dict[str, np.ndarray]]:
        return self.session.render_lidar(sensor_to_world, timestamp, beam_model, fmt="npz")

    def actors_at(self, timestamp: int) -> list[dict]:
        return self.session.actors_at(timestamp)
