"""``omnire bench serve RUN``: latency of renders through a real ``omnire serve`` process
(started on a free port, stopped at the end): one camera (``/render_image``) and the whole
rig (``/render_rig``) at ``--width`` x ``--height``, with 1 and 4 concurrent clients, each
request timed end to end by the client (HTTP, rendering, encoding, decoding), and split by
the server's ``Server-Timing`` into render (waiting for the render lock included), encode
and the rest (HTTP, JSON, the client's decoding). Poses and times cycle through the
recorded frames. Writes JSON (``--output``) and prints a table."""
from __future__ import annotations

import dataclasses
import json
import os
import platform
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np
import tyro

from omnire.api import ConfigError, atomic_write_text
from omnire_serve.client import OmnireClient
from omnire_serve.process import ServerProcess


@dataclasses.dataclass
class BenchServeArgs:
    """Render latency through omnire serve."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train (e.g. the trained demo run)."""
    requests: int = 20
    """Timed requests per client and case (after 2 untimed ones per client)."""
    width: int = 480
    height: int = 270
    clients: tuple[int, ...] = (1, 4)
    """Numbers of concurrent clients to measure."""
    threads: int = 0
    """The server's torch threads (0: torch's default)."""
    output: Optional[Path] = None
    """JSON file to write (default: print only)."""


def _time_requests(url: str, clients: int, n: int, call) -> list[tuple[float, float, float]]:
    """(seconds end to end, render, encode) of each of ``n`` timed requests of every
    client (``clients`` threads); the last two as the server reported them."""
    out: list[tuple[float, float, float]] = []
    lock = threading.Lock()
    errors: list[BaseException] = []

    def work(k: int) -> None:
        try:
            with OmnireClient(url, session=f"bench{k}") as client:
                for i in range(n + 2):
                    t0 = time.perf_counter()
                    call(client, i + k)
                    dt = time.perf_counter() - t0
                    if i >= 2:
                        st = client.server_timing
                        with lock:
                            out.append((dt, st.get("render", float("nan")), st.get("encode", float("nan"))))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the main thread
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return out


def run_bench(args: BenchServeArgs) -> dict:
    if args.requests <= 0 or not args.clients or min(args.clients) <= 0:
        raise ConfigError("--requests and --clients must be positive")
    extra = ["--threads", str(args.threads)] if args.threads else []
    extra += ["--max-pixels", str(max(args.width * args.height, 1))]
    server = ServerProcess(args.run_dir, extra, dict(os.environ))
    server.wait_ready()
    try:
        with OmnireClient(server.url) as client:
            meta = client.metadata()
        stamps = meta["time"]["frame_timestamps_us"]
        rig = np.asarray(meta["ego"]["rig_to_world"])
        cam = meta["cameras"][0]
        mount = np.asarray(cam["camera_to_rig"])
        size = (args.width, args.height)

        def camera(client, i):
            f = i % len(stamps)
            client.render_image(rig[f] @ mount, stamps[f], cam["name"], "raw", size)

        def whole_rig(client, i):
            f = i % len(stamps)
            client.render_rig(rig[f], stamps[f], None, size, "raw")

        rows = []
        for case, call in (("camera", camera), ("rig", whole_rig)):
            for n_clients in args.clients:
                t0 = time.perf_counter()
                timed = np.asarray(_time_requests(server.url, n_clients, args.requests, call))
                wall = time.perf_counter() - t0
                lat, render, encode = timed[:, 0], timed[:, 1], timed[:, 2]
                rows.append({"case": case, "cameras": 1 if case == "camera" else len(meta["cameras"]),
                             "clients": n_clients, "requests": int(lat.size),
                             "p50_ms": round(float(np.percentile(lat, 50)) * 1e3, 1),
                             "p95_ms": round(float(np.percentile(lat, 95)) * 1e3, 1),
                             "render_p50_ms": round(float(np.percentile(render, 50)) * 1e3, 1),
                             "encode_p50_ms": round(float(np.percentile(encode, 50)) * 1e3, 1),
                             "rest_p50_ms": round(float(np.percentile(lat - render - encode, 50)) * 1e3, 1),
                             "requests_per_s": round(n_clients * (args.requests + 2) / wall, 2)})
    finally:
        server.stop()
    return {"run": str(args.run_dir.resolve()), "size": list(size), "scene": meta["scene"],
            "machine": {"cpus": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2),
                        "python": platform.python_version()},
            "results": rows}


def table(result: dict) -> str:
    w, h = result["size"]
    header = (f"| case ({w}x{h}) | cameras | clients | p50 ms | p95 ms | render p50 | encode p50 | rest p50 | "
              "requests/s |")
    lines = [header, "|---|---|---|---|---|---|---|---|---|"]
    for r in result["results"]:
        lines.append(f"| {r['case']} | {r['cameras']} | {r['clients']} | {r['p50_ms']} | {r['p95_ms']} | "
                     f"{r['render_p50_ms']} | {r['encode_p50_ms']} | {r['rest_p50_ms']} | {r['requests_per_s']} |")
    return "\n".join(lines)


def main(argv: list[str], plugins) -> int:
    args = tyro.cli(BenchServeArgs, args=argv, prog="omnire bench serve")
    result = run_bench(args)
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.output, json.dumps(result, indent=1) + "\n")
    print(table(result))
    print(f"(load average at the end: {result['machine']['load_average_1min']} on {result['machine']['cpus']} cpus)")
    return 0
