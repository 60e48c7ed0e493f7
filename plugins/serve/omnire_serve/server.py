"""The HTTP application of ``omnire serve`` (FastAPI): neurad-studio's closed-loop endpoints
(``/alive``, ``/start_time``, ``/get_actors``, ``/update_actors``, ``/render_image``) with
their request and response shapes, and omnire's own (``/metadata``, ``/render_rig``,
``/render_lidar``, ``/actors_at``, ``/scenario``, ``/reset``). docs/closed_loop.md is the reference.

Every refusal is JSON ``{"error": {"field": ..., "message": ...}}`` with a 4xx status;
a failure inside the renderer is a 500 with the same shape; the server keeps serving.
Sessions: the ``X-Omnire-Session`` header names the episode a request acts on (default
``default``); each has its own edits and actor trajectories. Image responses carry a
``Server-Timing`` header: ``render`` (waiting for the render lock included) and ``encode``,
in milliseconds (``omnire bench serve`` reports them beside the client's latency).
"""
from __future__ import annotations

import base64
import hmac
import json
import logging
import re
import threading
import time
from typing import Any, Optional

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from omnire_serve.errors import RequestError
from omnire_serve.imaging import FORMATS, encode
from omnire_serve.lidar import FORMATS as LIDAR_FORMATS
from omnire_serve.lidar import encode_points
from omnire_serve.served import Episode, ServedScene

SESSION_HEADER = "X-Omnire-Session"
_SESSION_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
log = logging.getLogger("omnire.serve")


class BodyLimit:
    """ASGI middleware: a request body longer than ``limit`` bytes is refused with a 413
    JSON error before it is read whole."""

    def __init__(self, app, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.limit:
            return await _send_error(send, RequestError("body", f"{int(length)} bytes is more than the limit of "
                                                                f"{self.limit}", 413))
        seen = 0

        async def limited():
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:  # answered by the app's RequestError handler
                    raise RequestError("body", f"more than the limit of {self.limit} bytes", 413)
            return message

        await self.app(scope, limited, send)


async def _send_error(send, err: RequestError) -> None:
    body = json.dumps(err.as_json()).encode()
    await send({"type": "http.response.start", "status": err.status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


class Sessions:
    """Episodes by session id, at most ``limit`` of them."""

    def __init__(self, served: ServedScene, limit: int) -> None:
        self.served, self.limit = served, limit
        self.episodes: dict[str, Episode] = {}
        self.lock = threading.Lock()

    def get(self, request: Request) -> Episode:
        sid = request.headers.get(SESSION_HEADER, "default")
        if not _SESSION_ID.match(sid):
            raise RequestError(SESSION_HEADER, "expected 1 to 64 characters of A-Z a-z 0-9 . _ -")
        with self.lock:
            if sid not in self.episodes:
                if len(self.episodes) >= self.limit:
                    raise RequestError(SESSION_HEADER, f"{self.limit} sessions are open (omnire serve "
                                                       "--max-sessions); reuse one", 429)
                self.episodes[sid] = Episode(self.served)
            return self.episodes[sid]


async def _body(request: Request) -> Any:
    raw = await request.body()
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise RequestError("body", f"malformed JSON ({exc})") from None


def _field(data: dict, key: str, default: Any = ...) -> Any:
    if not isinstance(data, dict):
        raise RequestError("body", "expected a JSON object")
    if key not in data:
        if default is ...:
            raise RequestError(key, "missing")
        return default
    return data[key]


def _format(data: dict, default: str) -> str:
    fmt = _field(data, "image_format", default)
    if fmt not in FORMATS:
        raise RequestError("image_format", f"{fmt!r}: expected one of {list(FORMATS)}")
    return fmt


def server_timing(render: float, encode: float) -> dict[str, str]:
    """The ``Server-Timing`` header of an image response: render and encode seconds, as ms."""
    return {"Server-Timing": f"render;dur={render * 1e3:.2f}, encode;dur={encode * 1e3:.2f}"}


def create_app(served: ServedScene, token: Optional[str] = None) -> FastAPI:
    """The application serving ``served``; ``token``: every request must carry
    ``Authorization: Bearer <token>`` (None: no token asked)."""
    app = FastAPI(title="omnire serve", docs_url=None, redoc_url=None, openapi_url=None)
    sessions = Sessions(served, served.limits.max_sessions)
    app.add_middleware(BodyLimit, limit=served.limits.max_body_bytes)

    @app.middleware("http")
    async def authorize(request: Request, call_next):
        if token is not None:
            given = request.headers.get("authorization", "")
            if not hmac.compare_digest(given.encode(), f"Bearer {token}".encode()):
                err = RequestError("Authorization", "missing or wrong token (send 'Authorization: Bearer <token>')",
                                   401)
                return JSONResponse(err.as_json(), status_code=401)
        return await call_next(request)

    @app.exception_handler(RequestError)
    async def refused(request: Request, exc: RequestError):
        return JSONResponse(exc.as_json(), status_code=exc.status)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        field = "path" if exc.status_code in (404, 405) else ""
        return JSONResponse(RequestError(field, f"{request.method} {request.url.path}: {exc.detail}").as_json(),
                            status_code=exc.status_code)

    @app.exception_handler(Exception)
    async def failed(request: Request, exc: Exception):
        log.exception("request %s %s failed", request.method, request.url.path)
        return JSONResponse(RequestError("", f"internal error: {type(exc).__name__}: {exc}").as_json(),
                            status_code=500)

    # ------------------------------------------------------------------ neurad-studio's API
    @app.get("/alive")
    async def alive() -> bool:
        return True

    @app.get("/start_time")
    async def start_time() -> int:
        return served.start_us

    @app.get("/get_actors")
    async def get_actors(request: Request):
        episode = sessions.get(request)
        return JSONResponse(await run_in_threadpool(episode.trajectories))

    @app.post("/update_actors")
    async def update_actors(request: Request):
        episode = sessions.get(request)
        data = await _body(request)
        await run_in_threadpool(episode.update_actors, data)
        return JSONResponse(None)

    @app.post("/render_image")
    async def render_image(request: Request):
        episode = sessions.get(request)
        data = await _body(request)
        c = served.camera_index(_field(data, "camera_name"))
        pose = served.pose(_field(data, "pose"), "pose")
        seconds = served.seconds_at(_field(data, "timestamp"))
        fmt = _format(data, "raw")
        size = served.size_of(_field(data, "width", None), _field(data, "height", None), c)
        clock = time.perf_counter()
        image = await run_in_threadpool(episode.render_camera, c, pose, seconds, size)
        rendered = time.perf_counter()
        content, media = encode(image, fmt)
        return Response(content=content, media_type=media,
                        headers=server_timing(rendered - clock, time.perf_counter() - rendered))

    # ------------------------------------------------------------------ omnire's own
    @app.get("/metadata")
    async def metadata():
        return JSONResponse(await run_in_threadpool(served.metadata))

    async def posed(request: Request) -> tuple[Episode, Any, Any, float]:
        """(episode, body, checked 4x4 ``pose``, seconds of ``timestamp``) of a render request."""
        episode = sessions.get(request)
        data = await _body(request)
        return episode, data, served.pose(_field(data, "pose"), "pose"), served.seconds_at(_field(data, "timestamp"))

    @app.post("/render_rig")
    async def render_rig(request: Request):
        episode, data, rig, seconds = await posed(request)
        names = _field(data, "cameras", None)
        if names is None:
            cams = list(range(len(served.camera_names)))
        elif isinstance(names, list) and names:
            cams = [served.camera_index(n, f"cameras.{i}") for i, n in enumerate(names)]
        else:
            raise RequestError("cameras", "expected a non-empty list of camera names")
        fmt = _format(data, "png")
        sizes = [served.size_of(_field(data, "width", None), _field(data, "height", None), c) for c in cams]
        clock = time.perf_counter()
        images = await run_in_threadpool(episode.render_rig, rig, seconds, cams, sizes)
        rendered = time.perf_counter()
        out = {}
        for name, image in images.items():
            content, _ = encode(image, fmt)
            out[name] = {"width": image.shape[1], "height": image.shape[0], "format": fmt,
                         "data": content.decode() if fmt == "raw" else base64.b64encode(content).decode()}
        response = JSONResponse({"timestamp": data["timestamp"], "images": out})
        response.headers.update(server_timing(rendered - clock, time.perf_counter() - rendered))
        return response

    @app.post("/render_lidar")
    async def render_lidar(request: Request):
        episode, data, pose, seconds = await posed(request)
        model = served.beam_model(_field(data, "beam_model", None))
        fmt = _field(data, "format", "npz")
        if fmt not in LIDAR_FORMATS:
            raise RequestError("format", f"{fmt!r}: expected one of {list(LIDAR_FORMATS)}")
        rays = model.num_beams * model.num_azimuths
        if fmt == "json" and rays > served.limits.max_json_rays:
            raise RequestError("format", f"a sweep of {rays} rays is too large for JSON (at most "
                                         f"{served.limits.max_json_rays}); ask for npz", 413)
        points = await run_in_threadpool(episode.render_lidar, pose, seconds, model)
        content, media = encode_points(points, fmt)
        return Response(content=content, media_type=media)

    @app.post("/actors_at")
    async def actors_at(request: Request):
        episode = sessions.get(request)
        data = await _body(request)
        seconds = served.seconds_at(_field(data, "timestamp"))
        boxes = await run_in_threadpool(episode.boxes_at, seconds)
        return JSONResponse([b.as_json() for b in boxes])

    @app.post("/scenario")
    async def scenario(request: Request):
        episode = sessions.get(request)
        data = await _body(request)
        await run_in_threadpool(episode.set_scenario, data)
        return JSONResponse(_edits(episode))

    @app.get("/scenario")
    async def get_scenario(request: Request):
        return JSONResponse(_edits(sessions.get(request)))

    @app.post("/reset")
    async def reset(request: Request):
        episode = sessions.get(request)
        await run_in_threadpool(episode.reset)
        return JSONResponse(_edits(episode))

    return app


def _edits(episode: Episode) -> dict:
    """What an episode draws differently from the log."""
    out = []
    for a in episode.sim.actors:
        kind = "removed" if a.removed else ("inserted" if a.inserted else "edited")
        out.append({"id": a.key, "kind": kind, "node": a.node_name})
    return {"actors": out}
