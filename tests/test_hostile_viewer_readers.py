"""Hostile input to ``omnire view`` and to the nuScenes and Waymo readers (issue 41 items 2, 4, 6).

The viewer's limits are tested on a real ``omnire view`` process through a real websocket
client speaking viser's wire format (not through the page): every refused request ends with a
message to the client (a notification, or the close frame's reason) and the server keeps
serving. Command-line cases run through tests/hostile.py's ``run_case``.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from hostile import record, run_case
from scene_helpers import TINY_RUN_KEY, make_tiny_run

pytest.importorskip("viser")
msgspec = pytest.importorskip("msgspec")
zstandard = pytest.importorskip("zstandard")
websockets_sync = pytest.importorskip("websockets.sync.client")

MAX_RSS_BYTES = 3 << 30
"""The viewer of the tiny run stays far below this (about 1 GB); the unbounded requests of
issue 41 tried to allocate 4.8 and 23 GB."""
DEEP = 100_000


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    return make_tiny_run(tmp_path_factory.getbasetemp() / TINY_RUN_KEY)


# ---------------------------------------------------------------------------- a viser client
def decode(raw: bytes) -> list[dict]:
    """The messages of one server frame (viser's layout: two little-endian uint64 sizes, a
    zstd-compressed msgpack payload, binary buffers)."""
    size, compressed = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(raw[16:16 + compressed], max_output_size=size)
    return list(msgspec.msgpack.decode(inner)["messages"])


def strings_of(value) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [s for v in value.values() for s in strings_of(v)]
    if isinstance(value, (list, tuple)):
        return [s for v in value for s in strings_of(v)]
    return []


class Client:
    """A websocket client of the viewer: sends viser messages, collects what the server sends."""

    def __init__(self, url: str, **kw) -> None:
        import viser

        self.ws = websockets_sync.connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None,
                                          open_timeout=30, **kw)
        self.messages: list[dict] = []
        self.closed = None

    def send(self, message: dict) -> None:
        self.ws.send(msgspec.msgpack.encode(message))

    def send_raw(self, raw: bytes) -> None:
        self.ws.send(raw)

    def pump(self, seconds: float) -> None:
        from websockets.exceptions import ConnectionClosed

        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and self.closed is None:
            try:
                raw = self.ws.recv(timeout=max(0.01, deadline - time.monotonic()))
            except TimeoutError:
                return
            except ConnectionClosed as exc:
                self.closed = exc.rcvd
                return
            self.messages.extend(decode(raw))

    def wait_for(self, predicate, seconds: float = 30.0):
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and self.closed is None:
            found = [m for m in self.messages if predicate(m)]
            if found:
                return found[-1]
            self.pump(0.3)
        found = [m for m in self.messages if predicate(m)]
        return found[-1] if found else None

    def uuid_of(self, label: str) -> str:
        m = self.wait_for(lambda m: isinstance(m.get("props"), dict) and m["props"].get("label") == label)
        assert m is not None, f"no control labelled {label!r}"
        return m["uuid"]

    def notification(self, needle: str, seconds: float = 30.0):
        return self.wait_for(lambda m: m.get("type") == "NotificationShowMessage"
                             and any(needle in s for s in strings_of(m)), seconds)

    def camera(self, **override) -> None:
        message = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 1.5],
                   "fov": 1.0, "near": 0.01, "far": 1000.0, "image_height": 360, "image_width": 640,
                   "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, 0.0, 1.0]}
        message.update(override)
        self.send(message)

    def set_value(self, uuid: str, value) -> None:
        self.send({"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}})

    def close(self) -> None:
        self.ws.close()


class ViewerProcess:
    """``omnire view`` as its own process; :attr:`url` from the line it prints."""

    def __init__(self, run: Path, *args: str, env: dict | None = None) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "omnire.cli", "view", str(run), "--port", "0",
                                      "--seconds", "600", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="400", **(env or {})))
        self.lines: list[str] = []
        deadline = time.monotonic() + 180
        self.url = None
        while self.url is None:
            line = self.proc.stdout.readline()
            assert line or self.proc.poll() is None, "the viewer exited:\n" + "".join(self.lines)
            assert time.monotonic() < deadline, "the viewer did not start:\n" + "".join(self.lines)
            self.lines.append(line)
            found = re.search(r"omnire view: (http://\S+)", line)
            if found:
                self.url = found.group(1)
        if "--host" in args and "127.0.0.1" not in args:  # the banner's second line (same write)
            self.lines.append(self.proc.stdout.readline())
        self.port = int(re.search(r":(\d+)(?:/|$)", self.url).group(1))

    def ws_url(self, query: str = "") -> str:
        return f"ws://127.0.0.1:{self.port}/{query}"

    def peak_rss(self) -> int:
        text = Path(f"/proc/{self.proc.pid}/status").read_text()
        return int(re.search(r"VmHWM:\s+(\d+) kB", text).group(1)) * 1024

    def serves(self, query: str = "") -> bool:
        """The page is served and a new client gets the scene."""
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/{query}", timeout=10) as r:
            if r.status != 200:
                return False
        client = Client(self.ws_url(query))
        try:
            client.camera()
            return client.wait_for(lambda m: m.get("type") == "GaussianSplatsMessage") is not None
        finally:
            client.close()

    def stop(self) -> str:
        self.proc.terminate()
        try:
            out, _ = self.proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        return "".join(self.lines) + (out or "")


@pytest.fixture(scope="module")
def viewer(tiny_run):
    v = ViewerProcess(tiny_run)
    yield v
    v.stop()


def _ws_case(viewer: ViewerProcess, name: str, body) -> None:
    """Run ``body(client)`` on a fresh connected client; record it as a view case: it must
    end with a message to the client, the server within its memory cap and still serving."""
    client = Client(viewer.ws_url())
    traceback = None
    try:
        client.camera()
        ok = bool(body(client))
    except AssertionError as exc:
        ok, traceback = False, None
        detail = str(exc)
    else:
        detail = ""
    finally:
        client.close()
    rss = viewer.peak_rss()
    alive = viewer.proc.poll() is None and viewer.serves()
    record("view", f"websocket: {name}", exit=0 if ok and alive else 1, traceback=traceback,
           wrong=not (ok and alive and rss < MAX_RSS_BYTES))
    assert ok, f"{name}: {detail}"
    assert rss < MAX_RSS_BYTES, f"{name}: the viewer's peak memory reached {rss / 2**30:.1f} GiB"
    assert alive, f"{name}: the viewer stopped serving"


def _refused_by_close(needle: str):
    def check(client: Client) -> bool:
        client.pump(10)
        assert client.closed is not None, "the connection stayed open"
        assert client.closed.code in (1008, 1009) and needle in client.closed.reason, \
            f"closed with {client.closed.code} {client.closed.reason!r}"
        return True

    return check


def test_render_width_from_a_client_is_capped(viewer):
    """Issue 41 item 2: a width of 10^9 set by a client (the page's slider stops at 1920) is
    refused with a notification before any work, and the server keeps serving."""
    def body(client: Client) -> bool:
        width, button = client.uuid_of("Width (px)"), client.uuid_of("Render this view on the server")
        client.set_value(width, 10**9)
        client.set_value(button, True)
        note = client.notification("Width (px) 1000000000")
        assert note is not None, "no refusal reached the client"
        assert any("160..1920" in s for s in strings_of(note))
        return True

    _ws_case(viewer, "render width 10^9", body)


def test_huge_canvas_is_refused(viewer):
    """The client's canvas size feeds the server render: 10^9 pixels is refused (close 1008)."""
    _ws_case(viewer, "canvas 10^9 x 10^9", lambda c: (c.camera(image_width=10**9, image_height=10**9),
                                                     _refused_by_close("image_width")(c))[1])


@pytest.mark.parametrize("field,value,needle", [
    ("position", [float("nan"), 0.0, 0.0], "position"),
    ("wxyz", [0.0, 0.0, 0.0, 0.0], "wxyz"),
    ("fov", 1e9, "fov"),
    ("position", [1e300, 0.0, 0.0], "position"),
])
def test_bad_camera_pose_is_refused(viewer, field, value, needle):
    _ws_case(viewer, f"camera {field} = {value}", lambda c: (c.camera(**{field: value}),
                                                             _refused_by_close(needle)(c))[1])


def test_frame_outside_the_log_is_refused(viewer):
    def body(client: Client) -> bool:
        frame = client.uuid_of("Frame")
        for value in (1e9, -3.0):
            client.set_value(frame, value)
            assert client.notification(f"Frame {value}") is not None, f"frame {value} was not refused"
        return True

    _ws_case(viewer, "frame 1e9 and -3", body)


def test_offset_and_turn_limits(viewer):
    def body(client: Client) -> bool:
        client.set_value(client.uuid_of("Selected"), "car_000")
        time.sleep(1.0)  # the selection enables the edit fields
        client.set_value(client.uuid_of("Offset (m)"), [1e308, 0.0, 0.0])
        assert client.notification("Offset (m)") is not None, "an offset of 1e308 m was not refused"
        client.set_value(client.uuid_of("Turn (deg)"), 1e12)
        assert client.notification("Turn (deg)") is not None, "a turn of 1e12 degrees was not refused"
        client.set_value(client.uuid_of("Selected"), "nobody")
        assert client.notification("nobody") is not None, "an unknown actor was not refused"
        return True

    _ws_case(viewer, "offset 1e308, turn 1e12, unknown actor", body)


def test_lidar_controls_from_a_client(viewer):
    """The tiny run learned no LiDAR: its disabled "Rendered sweep" box ticked by a client,
    and a colour outside the dropdown's choices, are refused with a notification."""
    def body(client: Client) -> bool:
        client.set_value(client.uuid_of("Rendered sweep"), True)
        assert client.notification("this run learned no LiDAR") is not None, "ticking the disabled box was not refused"
        client.set_value(client.uuid_of("Colour by"), "x" * 1000)
        assert client.notification("Colour by") is not None, "an unknown colour was not refused"
        return True

    _ws_case(viewer, "LiDAR sweep on a run without LiDAR, unknown colour", body)


def test_a_client_cannot_change_a_controls_range(viewer):
    def body(client: Client) -> bool:
        client.send({"type": "GuiUpdateMessage", "uuid": client.uuid_of("Width (px)"), "updates": {"max": 10**9}})
        return _refused_by_close("max")(client)

    _ws_case(viewer, "slider max from a client", body)


@pytest.mark.parametrize("name,raw,needle", [
    ("2 MiB message", b"\x00" * (2 << 20), ""),
    ("not msgpack", b"\xc1\xc1\xc1garbage", "not a viser message"),
    ("nested 200k deep", b"\x91" * 200_000 + b"\x00", "not a viser message"),
])
def test_malformed_and_oversized_messages(viewer, name, raw, needle):
    _ws_case(viewer, name, lambda c: (c.send_raw(raw), _refused_by_close(needle)(c))[1])


def test_non_loopback_bind_needs_the_token(tiny_run):
    """--host 0.0.0.0: the printed URL is the real address with a token; without it the page
    and the websocket are refused (401), with it (in the URL, then the cookie it sets) the
    viewer works; --token / OMNIRE_VIEW_TOKEN choose the token."""
    viewer = ViewerProcess(tiny_run, "--host", "0.0.0.0", env={"OMNIRE_VIEW_TOKEN": "s3cret-token"})
    try:
        out = "".join(viewer.lines)
        assert "127.0.0.1" not in viewer.url and viewer.url.endswith("/?token=s3cret-token"), out
        refused = []
        for query in ("", "?token=wrong"):
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}/{query}", timeout=10)
            except urllib.error.HTTPError as exc:
                refused.append(exc.code)
            from websockets.exceptions import InvalidStatus

            with pytest.raises(InvalidStatus, match="401"):
                Client(viewer.ws_url(query))
        assert refused == [401, 401]
        with urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}/?token=s3cret-token", timeout=10) as r:
            cookie = r.headers["Set-Cookie"].split(";")[0]
        assert cookie == "omnire_view_token=s3cret-token"
        assert viewer.serves("?token=s3cret-token")
        client = Client(viewer.ws_url(), additional_headers={"Cookie": cookie})  # as the page's browser does
        client.camera()
        assert client.wait_for(lambda m: m.get("type") == "GaussianSplatsMessage") is not None
        client.close()
        ok = True
    finally:
        out = viewer.stop()
    assert "reachable from other machines" in out
    record("view", "--host 0.0.0.0 without the token", exit=0 if ok else 1, wrong=not ok)


# ---------------------------------------------------------------------------- command line
def _nested_toml(path: Path) -> Path:
    path.write_text("x = " + "[" * DEEP + "]" * DEEP + "\n")
    return path


VIEW_FLAGS = {
    "unknown device": (["--device", "banana"], "--device 'banana'"),
    "cuda on a cpu build": (["--device", "cuda"], "no usable CUDA"),
    "negative max gaussians": (["--max-gaussians", "-5"], "--max-gaussians -5"),
    "negative sky splats": (["--sky-splats", "-1"], "--sky-splats -1"),
    "negative seconds": (["--seconds", "-2"], "--seconds -2"),
    "nan seconds": (["--seconds", "nan"], "--seconds nan"),
}


@pytest.mark.parametrize("case", sorted(VIEW_FLAGS))
def test_view_flags(case, tiny_run, capsys):
    flags, needle = VIEW_FLAGS[case]
    if case == "cuda on a cpu build":
        import torch

        if torch.cuda.is_available():
            pytest.skip("this torch build has CUDA")
    run_case(f"view {case}", ["view", str(tiny_run), "--port", "0", "--seconds", "1", *flags], capsys, [tiny_run],
             needles=(needle,), surface="view")


def test_view_deeply_nested_inputs(tiny_run, tmp_path, capsys):
    scenario = _nested_toml(tmp_path / "deep.toml")
    run_case("view scenario nested 100k deep", ["view", str(tiny_run), "--port", "0", "--scenario", str(scenario)],
             capsys, [scenario, tiny_run], needles=("deep.toml", "nested more than 64 levels deep"), surface="view")
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    (run / "run.json").write_text('{"a": ' + "[" * DEEP + "]" * DEEP + "}")
    run_case("view run.json nested 100k deep", ["view", str(run), "--port", "0"], capsys, [run],
             needles=("run.json", "nested too deeply"), surface="view")


# ---------------------------------------------------------------------------- readers
@pytest.fixture(scope="module")
def nuscenes_scene(tmp_path_factory):
    pytest.importorskip("omnire_nuscenes")
    from omnire.plugins import load_plugins
    from omnire_synthetic.cli import main as synth_main

    scene = tmp_path_factory.mktemp("nus") / "tiny_nuscenes"
    assert synth_main(["urban", str(scene), "--tiny", "--format", "nuscenes"], load_plugins()) == 0
    return scene


READER_TRAIN = ["--trainer.max-steps", "1", "--trainer.no-progress", "--method.rasterizer", "torch"]


def _nuscenes_copy(nuscenes_scene: Path, tmp_path: Path) -> tuple[Path, Path]:
    from omnire_nuscenes.writer import VERSION

    scene = tmp_path / "nus"
    shutil.copytree(nuscenes_scene, scene)
    return scene, scene / VERSION


def test_nuscenes_timestamp_not_a_number(nuscenes_scene, tmp_path, capsys):
    scene, tables = _nuscenes_copy(nuscenes_scene, tmp_path)
    records = json.loads((tables / "sample_data.json").read_text())
    records[0]["timestamp"] = "abc"
    (tables / "sample_data.json").write_text(json.dumps(records))
    run_case("nuscenes timestamp 'abc'", ["train", "3dgs", "nuscenes", "--data", str(scene), *READER_TRAIN,
                                          "--trainer.output-dir", str(tmp_path / "runs")], capsys, [scene],
             needles=("sample_data.json", "'timestamp'", "'abc'"), surface="nuscenes")


def test_nuscenes_table_nested_deeply(nuscenes_scene, tmp_path, capsys):
    scene, tables = _nuscenes_copy(nuscenes_scene, tmp_path)
    (tables / "sensor.json").write_text("[" + "[" * DEEP + "]" * DEEP + "]")
    run_case("nuscenes table nested 100k deep", ["train", "3dgs", "nuscenes", "--data", str(scene), *READER_TRAIN,
                                                 "--trainer.output-dir", str(tmp_path / "runs")], capsys, [scene],
             needles=("sensor.json", "nested too deeply"), surface="nuscenes")


@pytest.mark.parametrize("layout", ["segment path", "segment in a folder"])
def test_waymo_segment_symlink_loop(layout, tmp_path, capsys):
    pytest.importorskip("omnire_waymo")
    folder = tmp_path / "data"
    folder.mkdir()
    loop = folder / "segment-loop_with_camera_labels.tfrecord"
    loop.symlink_to(loop.name)  # points at itself
    data = loop if layout == "segment path" else folder
    run_case(f"waymo {layout} is a symlink loop", ["train", "3dgs", "waymo", "--data", str(data), *READER_TRAIN,
                                                   "--trainer.output-dir", str(tmp_path / "runs")], capsys, [],
             needles=(loop.name, "symbolic link loop"), surface="waymo")
