"""How the environment reaches the scene: in the same process (:class:`LocalTransport`,
an :class:`~omnire_serve.served.Episode` of a ServedScene) or through ``omnire serve``
(:class:`HttpTransport`, an :class:`~omnire_serve.client.OmnireClient`). Both offer the same
five calls with the same values, so the environment does not know which it has."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from omnire_serve.client import OmnireClient
from omnire_serve.served import Episode, ServedScene


class LocalTransport:
    """The scene in this process."""

    def __init__(self, served: ServedScene) -> None:
        self.served = served
        self.episode = Episode(served)

    def metadata(self) -> dict:
        return self.served.metadata()

    def reset(self, scenario: Optional[dict]) -> None:
        self.episode.reset()
        if scenario:
            self.episode.set_scenario(scenario)

    def render_rig(self, rig_to_world: np.ndarray, timestamp: int, cameras: Sequence[str],
                   size: Optional[tuple[int, int]]) -> dict[str, np.ndarray]:
        s = self.served
        pose = s.pose(rig_to_world, "pose")
        cams = [s.camera_index(n, "cameras") for n in cameras]
        sizes = [s.size_of(*(size or (None, None)), c) for c in cams]
        return self.episode.render_rig(pose, s.seconds_at(timestamp), cams, sizes)

    def actors_at(self, timestamp: int) -> list[dict]:
        return [b.as_json() for b in self.episode.boxes_at(self.served.seconds_at(timestamp))]


class HttpTransport:
    """The scene behind an ``omnire serve`` server."""

    def __init__(self, client: OmnireClient) -> None:
        self.client = client

    def metadata(self) -> dict:
        return self.client.metadata()

    def reset(self, scenario: Optional[dict]) -> None:
        self.client.reset()
        if scenario:
            self.client.set_scenario(scenario)

    def render_rig(self, rig_to_world: np.ndarray, timestamp: int, cameras: Sequence[str],
                   size: Optional[tuple[int, int]]) -> dict[str, np.ndarray]:
        return self.client.render_rig(rig_to_world, timestamp, cameras, size, image_format="raw")

    def actors_at(self, timestamp: int) -> list[dict]:
        return self.client.actors_at(timestamp)
