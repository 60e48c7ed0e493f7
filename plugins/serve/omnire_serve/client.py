"""A Python client of ``omnire serve`` (httpx): every endpoint as a method, images as
(H, W, 3) uint8 arrays, LiDAR sweeps as (meta, field arrays), refusals raised as
:class:`ServerRefused` with the server's field and message."""
from __future__ import annotations

import base64
import contextlib
from typing import Optional, Sequence

import httpx
import numpy as np

from omnire_serve.imaging import decode
from omnire_serve.lidar import decode_points
from omnire_serve.server import SESSION_HEADER


class ServerRefused(Exception):
    """The server answered with an error: ``status``, ``field``, ``message``."""

    def __init__(self, status: int, field: str, message: str) -> None:
        super().__init__(f"{status} {field}: {message}")
        self.status, self.field, self.message = status, field, message


def parse_server_timing(header: str) -> dict[str, float]:
    """``Server-Timing`` entries (``name;dur=ms, ...``) as seconds by name; entries
    without a duration are left out."""
    out = {}
    for entry in header.split(","):
        name, *params = (p.strip() for p in entry.split(";"))
        for p in params:
            key, _, value = p.partition("=")
            if name and key == "dur":
                try:
                    out[name] = float(value) / 1e3
                except ValueError:
                    pass
    return out


class OmnireClient(contextlib.AbstractContextManager):
    """A client of one server (``url``, e.g. ``http://127.0.0.1:8000``) in one session.
    ``token``: sent as ``Authorization: Bearer``; ``session``: the X-Omnire-Session id.
    ``server_timing``: the stages (seconds by name) the server reported for the last
    response (``Server-Timing``; empty when it sent none)."""

    def __init__(self, url: str, token: Optional[str] = None, session: str = "default",
                 timeout: float = 120.0) -> None:
        headers = {SESSION_HEADER: session}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        self.http = httpx.Client(base_url=url, headers=headers, timeout=timeout)
        self.server_timing: dict[str, float] = {}

    def close(self) -> None:
        self.http.close()

    def __exit__(self, *exc) -> None:
        self.close()

    def _check(self, r: httpx.Response) -> httpx.Response:
        self.server_timing = parse_server_timing(r.headers.get("server-timing", ""))
        if r.status_code >= 400:
            try:
                err = r.json()["error"]
                raise ServerRefused(r.status_code, err.get("field", ""), err.get("message", ""))
            except (ValueError, KeyError, TypeError):
                raise ServerRefused(r.status_code, "", r.text[:500]) from None
        return r

    def get(self, path: str):
        return self._check(self.http.get(path)).json()

    def post(self, path: str, data) -> httpx.Response:
        return self._check(self.http.post(path, json=data))

    # ------------------------------------------------------------------ endpoints
    def alive(self) -> bool:
        return bool(self.get("/alive"))

    def metadata(self) -> dict:
        return self.get("/metadata")

    def start_time(self) -> int:
        return int(self.get("/start_time"))

    def actors(self) -> list[dict]:
        return self.get("/get_actors")

    def update_actors(self, trajectories: list[dict]) -> None:
        self.post("/update_actors", trajectories)

    def actors_at(self, timestamp: int) -> list[dict]:
        return self.post("/actors_at", {"timestamp": int(timestamp)}).json()

    def set_scenario(self, tables: dict) -> dict:
        return self.post("/scenario", tables).json()

    def reset(self) -> dict:
        return self.post("/reset", {}).json()

    def render_image(self, camera_to_world: np.ndarray, timestamp: int, camera: str, image_format: str = "png",
                     size: Optional[tuple[int, int]] = None) -> np.ndarray:
        data = {"pose": np.asarray(camera_to_world, dtype=np.float64).tolist(), "timestamp": int(timestamp),
                "camera_name": camera, "image_format": image_format}
        if size is not None:
            data["width"], data["height"] = int(size[0]), int(size[1])
        return decode(self.post("/render_image", data).content, image_format)

    def render_lidar(self, sensor_to_world: np.ndarray, timestamp: int, beam_model: Optional[dict] = None,
                     fmt: str = "npz") -> tuple[dict, dict[str, np.ndarray]]:
        """(meta, field -> (P,) array) of one LiDAR revolution (omnire_serve.lidar); ``beam_model``
        as /render_lidar takes it (default: the scene's)."""
        data = {"pose": np.asarray(sensor_to_world, dtype=np.float64).tolist(), "timestamp": int(timestamp),
                "format": fmt}
        if beam_model is not None:
            data["beam_model"] = beam_model
        r = self.post("/render_lidar", data)
        return decode_points(r.content, r.headers.get("content-type", ""))

    def render_rig(self, rig_to_world: np.ndarray, timestamp: int, cameras: Optional[Sequence[str]] = None,
                   size: Optional[tuple[int, int]] = None, image_format: str = "raw") -> dict[str, np.ndarray]:
        data = {"pose": np.asarray(rig_to_world, dtype=np.float64).tolist(), "timestamp": int(timestamp),
                "image_format": image_format}
        if cameras is not None:
            data["cameras"] = list(cameras)
        if size is not None:
            data["width"], data["height"] = int(size[0]), int(size[1])
        images = self.post("/render_rig", data).json()["images"]
        return {name: decode(item["data"].encode() if image_format == "raw" else base64.b64decode(item["data"]),
                             image_format) for name, item in images.items()}
