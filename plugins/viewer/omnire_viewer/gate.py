"""The viewer's front door: the only socket a browser (or any other client) reaches.

viser serves its page and its websocket on a loopback port of its own; :class:`Gate` listens
on the address asked for (``--host`` / ``--port``) and relays to it, enforcing what viser
itself does not:

- **a token** on every request when a token is set (always for an address other machines
  can reach, see :func:`is_loopback`): ``?token=...`` in the page's URL (the page answer then
  sets a cookie, which the browser sends with the websocket handshake), the cookie, or an
  ``Authorization: Bearer ...`` header. Anything else is answered 401 before viser sees it;
- **a size cap** on every client message (:data:`MAX_MESSAGE_BYTES`; viser allows 50 MB) and
  a cap on the clients connected at once (:data:`MAX_CLIENTS`);
- **a message policy** (:func:`check_client_message`): only well-formed viser messages, GUI
  updates of a control's value only (a client cannot change a slider's range or enable a
  disabled control), finite numbers, camera image sizes and fields of view within bounds.

A refused message closes that client's connection with code 1008 and the reason in the close
frame (the client's message); the server keeps serving every other client and new ones.
Values that are well-formed but outside what a control allows (a render width above the
slider's maximum, a frame outside the log) are the application's to refuse, per client
(:mod:`omnire_viewer.app`).
"""
from __future__ import annotations

import asyncio
import hmac
import http
import ipaddress
import math
import socket
import threading
import urllib.error
import urllib.parse
import urllib.request
from http.cookies import SimpleCookie
from typing import Any, Callable, Optional

MAX_MESSAGE_BYTES = 1 << 20
"""A client message larger than this closes its connection (the page's largest, a camera
update, is a few hundred bytes)."""
MAX_CLIENTS = 16
"""Clients connected at once; the next handshake is answered 503."""
MAX_CANVAS_PIXELS = 16384
"""Largest canvas side a client may report (its camera's image_width / image_height)."""
MAX_COORDINATE = 1e7
"""Largest absolute coordinate (metres) of a client's camera or click ray."""
COOKIE = "omnire_view_token"


def is_loopback(host: str) -> bool:
    """True when every address ``host`` resolves to is a loopback address (only this machine
    can connect); False for ``0.0.0.0``, ``::``, an interface's address or a name that
    resolves to one."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror:
        return False
    addresses = {info[4][0].split("%", 1)[0] for info in infos}
    return bool(addresses) and all(ipaddress.ip_address(a).is_loopback for a in addresses)


def _finite_numbers(value: Any, path: str) -> Optional[str]:
    """The first non-finite number inside ``value`` (nested lists / tuples / dicts), named by
    its path, or None."""
    stack = [(value, path)]
    while stack:
        v, where = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            return f"{where} = {v}: expected a finite number"
        if isinstance(v, dict):
            stack.extend((x, f"{where}.{k}") for k, x in v.items())
        elif isinstance(v, (list, tuple)):
            stack.extend((x, f"{where}[{i}]") for i, x in enumerate(v))
    return None


def check_client_message(raw: bytes | str) -> Optional[str]:
    """Why a message from a client is refused (one line naming the message and field), or
    None when viser may handle it."""
    import dataclasses

    from viser import _messages  # the wire format of the viser version pinned in pyproject.toml

    if not isinstance(raw, bytes):
        return "text frame: viser messages are binary (msgpack)"
    try:
        message = _messages.Message.deserialize(raw)
    except Exception as exc:  # noqa: BLE001 - any decoding failure (msgpack, unknown type, nesting) is a refusal
        return f"not a viser message ({type(exc).__name__})"
    kind = type(message).__name__
    fields = {f.name: getattr(message, f.name) for f in dataclasses.fields(message)}
    bad = _finite_numbers(fields, kind)
    if bad is not None:
        return bad
    if isinstance(message, _messages.GuiUpdateMessage):
        extra = sorted(set(message.updates) - {"value"})
        if extra:
            return f"{kind}.updates: a client may change a control's value only, not {', '.join(map(str, extra))}"
    if isinstance(message, _messages.ViewerCameraMessage):
        for name in ("image_width", "image_height"):
            size = fields[name]
            if not isinstance(size, int) or not 0 <= size <= MAX_CANVAS_PIXELS:
                return f"{kind}.{name} = {size!r}: expected 0..{MAX_CANVAS_PIXELS} pixels"
        if not 0.0 < message.fov < math.pi:
            return f"{kind}.fov = {message.fov!r}: expected a vertical field of view in (0, pi) radians"
        if sum(q * q for q in message.wxyz) < 1e-12:
            return f"{kind}.wxyz = {message.wxyz!r}: expected a rotation quaternion (non-zero)"
    for name in ("position", "look_at", "ray_origin"):
        point = fields.get(name)
        if point is not None and any(abs(c) > MAX_COORDINATE for c in point):
            return f"{kind}.{name} = {point!r}: coordinates beyond {MAX_COORDINATE:g} m"
    return None


class Gate:
    """Listens on ``host:port`` and relays HTTP requests and websocket messages to viser on
    ``127.0.0.1:upstream_port``, under the rules of the module docstring.

    Args:
        host, port: where to listen (port 0: any free port; see :attr:`port`).
        upstream_port: the loopback port viser listens on.
        token: required on every request when set (None: no token asked).
        check: the message policy (:func:`check_client_message`).
        log: receives one line per refused request or message.
    """

    def __init__(self, host: str, port: int, upstream_port: int, token: Optional[str] = None,
                 check: Callable[[bytes | str], Optional[str]] = check_client_message,
                 log: Callable[[str], None] = print) -> None:
        self.host, self.token, self.check, self.log = host, token, check, log
        self.upstream = f"127.0.0.1:{upstream_port}"
        self.clients = 0
        self._loop = asyncio.new_event_loop()
        self._server = None
        ready, failure = threading.Event(), []

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._server = self._loop.run_until_complete(self._serve(host, port))
            except BaseException as exc:  # noqa: BLE001 - handed to the constructor's thread
                failure.append(exc)
                ready.set()
                return
            ready.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=run, name="omnire-viewer-gate", daemon=True)
        self._thread.start()
        ready.wait()
        if failure:
            raise failure[0]
        self.port = self._server.sockets[0].getsockname()[1]

    async def _serve(self, host: str, port: int):
        from websockets.asyncio.server import serve
        from websockets.typing import Subprotocol

        return await serve(self._relay, host, port, max_size=MAX_MESSAGE_BYTES, compression=None,
                           process_request=self._admit,
                           select_subprotocol=lambda _c, offered: next(
                               (Subprotocol(p) for p in offered if p.startswith("viser-v")), None))

    # ------------------------------------------------------------------ HTTP
    def _token_of(self, request) -> tuple[Optional[str], bool]:
        """(the token a request carries, whether it came in the URL)."""
        query = urllib.parse.parse_qs(urllib.parse.urlsplit(request.path).query)
        if query.get("token"):
            return query["token"][0], True
        auth = request.headers.get("Authorization", "")
        if auth.startswith("Bearer "):
            return auth[len("Bearer "):].strip(), False
        cookie = SimpleCookie()
        try:
            cookie.load(request.headers.get("Cookie", ""))
        except Exception:  # noqa: BLE001 - a malformed cookie header carries no token
            return None, False
        return (cookie[COOKIE].value if COOKIE in cookie else None), False

    async def _admit(self, connection, request):
        """Answer a request the gate refuses or that is not a websocket handshake (the page);
        None lets the handshake go on to :meth:`_relay`."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        given, in_url = self._token_of(request)
        if self.token is not None and not (given is not None
                                           and hmac.compare_digest(given.encode(), self.token.encode())):
            self.log(f"refused {connection.remote_address[0]}: {'wrong' if given else 'no'} token")
            return connection.respond(http.HTTPStatus.UNAUTHORIZED,
                                      "this viewer needs its token: open the URL printed when it started "
                                      "(http://HOST:PORT/?token=...)\n")
        if request.headers.get("Upgrade", "").lower() == "websocket":
            if self.clients >= MAX_CLIENTS:
                return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE,
                                          f"at most {MAX_CLIENTS} clients at once\n")
            return None
        status, headers, body = await asyncio.to_thread(self._fetch, request)
        if in_url and self.token is not None:
            headers.append(("Set-Cookie", f"{COOKIE}={self.token}; HttpOnly; SameSite=Strict; Path=/"))
        return Response(status.value, status.phrase, Headers(headers), body)

    def _fetch(self, request) -> tuple[http.HTTPStatus, list[tuple[str, str]], bytes]:
        """viser's answer to a page request (its static client)."""
        path = urllib.parse.urlsplit(request.path).path or "/"
        req = urllib.request.Request(f"http://{self.upstream}{path}",
                                     headers={"Accept-Encoding": request.headers.get("Accept-Encoding", "")})
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                body, status = r.read(), http.HTTPStatus(r.status)
                kept = [(k, v) for k, v in r.headers.items() if k.lower() in ("content-type", "content-encoding")]
        except urllib.error.HTTPError as exc:
            return http.HTTPStatus(exc.code), [("Content-Type", "text/plain")], b"not found\n"
        return status, kept + [("Content-Length", str(len(body)))], body

    # ------------------------------------------------------------------ websocket
    async def _relay(self, client) -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        self.clients += 1
        who = f"{client.remote_address[0]}:{client.remote_address[1]}"
        try:
            protocols = [client.subprotocol] if client.subprotocol else None
            async with connect(f"ws://{self.upstream}", subprotocols=protocols, max_size=None,
                               compression=None) as upstream:
                down = asyncio.create_task(self._forward(upstream, client))
                try:
                    async for raw in client:
                        reason = self.check(raw)
                        if reason is not None:
                            self.log(f"refused a message from {who}: {reason}")
                            await client.close(1008, _close_reason(reason))
                            break
                        await upstream.send(raw)
                finally:
                    down.cancel()
        except ConnectionClosed as exc:
            if exc.rcvd is None and exc.sent is not None and exc.sent.code == 1009:
                self.log(f"refused a message from {who}: larger than {MAX_MESSAGE_BYTES} bytes")
        except OSError as exc:
            self.log(f"viewer unreachable for {who}: {exc}")
        finally:
            self.clients -= 1

    @staticmethod
    async def _forward(upstream, client) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            async for raw in upstream:
                await client.send(raw)
        except ConnectionClosed:
            pass
        await client.close()

    def close(self) -> None:
        if self._server is not None and self._loop.is_running():
            async def shut() -> None:
                self._server.close()
                await self._server.wait_closed()

            asyncio.run_coroutine_threadsafe(shut(), self._loop).result(10)
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)


def _close_reason(text: str) -> str:
    """``text`` cut to the 123 bytes a websocket close reason may hold."""
    data = text.encode("utf-8")[:123]
    return data.decode("utf-8", "ignore")
