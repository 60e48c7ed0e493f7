"""``omnire serve RUN``: load a trained run and serve it over HTTP (server.py) until Ctrl-C
or SIGTERM, which finish the requests in flight and exit 0.

Safe by default: binds 127.0.0.1; any other address needs a token (the environment variable
OMNIRE_SERVE_TOKEN or --token-file), which every request must then carry.
"""
from __future__ import annotations

import dataclasses
import ipaddress
import os
import signal
import socket
from pathlib import Path
from typing import Optional

import torch
import tyro

from omnire.api import ConfigError, Reconstruction
from omnire_serve.checks import Limits
from omnire_serve.served import ServedScene
from omnire_sim import load_scenario

TOKEN_ENV = "OMNIRE_SERVE_TOKEN"


@dataclasses.dataclass
class ServeArgs:
    """Serve a trained scene for closed-loop driving (docs/closed_loop.md)."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    host: str = "127.0.0.1"
    """Address to bind. Anything but a loopback address needs a token."""
    port: int = 8000
    """Port (0: any free port; the one taken is printed)."""
    token_file: Optional[Path] = None
    """File holding the token requests must carry (default: $OMNIRE_SERVE_TOKEN, if set)."""
    scenario: Optional[Path] = None
    """Scenario file (TOML, docs/simulation.md) every episode starts from and resets to."""
    checkpoint: Optional[Path] = None
    """Checkpoint file (default: the run's newest intact one)."""
    assets: Optional[Path] = None
    """Directory whose runs and motion files client scenarios may use (default: none)."""
    margin: float = Limits.margin
    """Metres a pose may lie outside the scene (the box around its cameras, actors and LiDAR points)."""
    max_pixels: int = Limits.max_pixels
    """Most pixels of one rendered image."""
    max_sessions: int = Limits.max_sessions
    """Most sessions (X-Omnire-Session ids) held at once."""
    max_lidar_rays: int = Limits.max_lidar_rays
    """Most rays of one rendered LiDAR revolution (beams x azimuth steps)."""
    threads: int = 0
    """Torch threads for rendering (0: torch's default)."""


def read_token(args: ServeArgs) -> Optional[str]:
    if args.token_file is not None:
        try:
            token = args.token_file.read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"--token-file {args.token_file}: cannot read it ({exc})") from None
        if not token:
            raise ConfigError(f"--token-file {args.token_file}: empty")
        return token
    return os.environ.get(TOKEN_ENV) or None


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host``:``port`` (errors name the flag)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ConfigError(f"--host {host}: cannot resolve it ({exc})") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(addr)
    except OSError as exc:
        sock.close()
        raise ConfigError(f"--host {host} --port {port}: cannot bind ({exc.strerror})") from None
    sock.listen(64)
    return sock


def main(argv: list[str], plugins) -> int:
    import uvicorn

    from omnire_serve.server import create_app

    args = tyro.cli(ServeArgs, args=argv, prog="omnire serve")
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: expected 0 .. 65535")
    token = read_token(args)
    if token is None and not is_loopback(args.host):
        raise ConfigError(f"--host {args.host}: not a loopback address; serving it needs a token "
                          f"(set {TOKEN_ENV} or pass --token-file)")
    if args.margin < 0 or args.max_pixels <= 0 or args.max_sessions <= 0 or args.max_lidar_rays <= 0:
        raise ConfigError("--margin must be >= 0, --max-pixels, --max-sessions and --max-lidar-rays > 0")
    if args.assets is not None and not args.assets.is_dir():
        raise ConfigError(f"--assets {args.assets}: not a directory")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    scenario = load_scenario(args.scenario) if args.scenario is not None else None
    limits = Limits(margin=args.margin, max_pixels=args.max_pixels, max_sessions=args.max_sessions,
                    max_lidar_rays=args.max_lidar_rays)
    recon = Reconstruction.from_run(args.run_dir, plugins, args.checkpoint)
    served = ServedScene(recon, plugins, scenario, limits, args.assets)
    served.corridor  # noqa: B018 - computed before the first client waits for it
    sock = bind(args.host, args.port)
    port = sock.getsockname()[1]
    app = create_app(served, token)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False, limit_max_requests=None,
                                          timeout_graceful_shutdown=10))
    print(f"omnire serve: {recon.scene.name} listening on http://{args.host}:{port}"
          + (" (token required)" if token else ""), flush=True)
    # uvicorn turns Ctrl-C / SIGTERM into a graceful shutdown and then raises the signal again
    # for the handler it found installed: this one, so the process ends normally (exit 0)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: None)
    server.run(sockets=[sock])
    print("omnire serve: stopped", flush=True)
    return 0
