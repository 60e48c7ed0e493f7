"""``omnire serve`` as a process, driven over real HTTP: a client written to neurad-studio's
closed-loop API, pixels against ``omnire sim``, hostile requests, sessions, the token."""
from __future__ import annotations

import base64
import io
import json
import subprocess
import threading

import httpx
import numpy as np
import pytest
import torch
from PIL import Image

from serve_helpers import OMNIRE, TOKEN, clean_env, hostile_request
from hostile import record

WHITE_CAR = "8ac00bad-822c-4040-b9a2-31424dbcd486"


class NeuradStyleClient:
    """Requests and responses exactly as neurad-studio's closed-loop API has them: GET
    /alive -> true, GET /start_time -> microseconds, GET /get_actors -> [{uuid, poses (N x 4
    x 4), timestamps (N, microseconds), dims (3)}], POST /update_actors with that list, POST
    /render_image {pose 4x4, timestamp, camera_name, image_format} -> raw (base64 of a
    torch.save'd uint8 H x W x 3 tensor), png or jpeg bytes."""

    def __init__(self, url: str) -> None:
        self.http = httpx.Client(base_url=url, timeout=300)

    def alive(self) -> bool:
        return self.http.get("/alive").json()

    def start_time(self) -> int:
        return self.http.get("/start_time").json()

    def get_actors(self) -> list[dict]:
        return self.http.get("/get_actors").json()

    def update_actors(self, actors: list[dict]) -> None:
        r = self.http.post("/update_actors", json=actors)
        assert r.status_code == 200, r.text
        assert r.json() is None

    def render(self, pose, timestamp: int, camera_name: str, image_format: str = "raw") -> np.ndarray:
        r = self.http.post("/render_image", json={"pose": pose, "timestamp": timestamp, "camera_name": camera_name,
                                                  "image_format": image_format})
        assert r.status_code == 200, r.text
        if image_format == "raw":
            return torch.load(io.BytesIO(base64.b64decode(r.content))).numpy()
        return np.asarray(Image.open(io.BytesIO(r.content)))


def _recorded_camera(served, c: int, frame: int) -> list:
    return np.asarray(served.recon.scene.cameras[c].cam_to_world[frame], dtype=np.float64).tolist()


def test_neurad_style_client(server, served):
    api = NeuradStyleClient(server.url)
    assert api.alive() is True
    start = api.start_time()
    assert start == served.start_us
    actors = api.get_actors()
    assert {a["uuid"] for a in actors} == set(served.actor_ids)
    car = next(a for a in actors if a["uuid"] == WHITE_CAR)
    assert np.asarray(car["poses"]).shape == (len(car["timestamps"]), 4, 4) and len(car["dims"]) == 3
    assert car["timestamps"][0] == start
    pose, stamp = _recorded_camera(served, 0, 5), int(served.frame_us[5])
    raw = api.render(pose, stamp, "front_camera")
    png = api.render(pose, stamp, "front_camera", "png")
    jpg = api.render(pose, stamp, "CAM_front_camera", "jpeg")
    cam = served.recon.scene.cameras[0]
    assert raw.shape == (cam.height, cam.width, 3) and raw.dtype == np.uint8 and raw.std() > 1
    assert np.array_equal(raw, png)
    assert np.abs(jpg.astype(int) - png).mean() < 8
    # the white car moved 4 m to the left over its whole track: get_actors shows it there
    moved = json.loads(json.dumps(car))
    for P in moved["poses"]:
        P[1][3] += 4.0
    api.update_actors([moved if a["uuid"] == WHITE_CAR else a for a in actors])
    after = {a["uuid"]: a for a in api.get_actors()}
    assert set(after) == set(served.actor_ids)
    assert np.allclose(np.asarray(after[WHITE_CAR]["poses"])[:, :3, 3], np.asarray(moved["poses"])[:, :3, 3], atol=1e-3)
    unchanged = next(u for u in after if u != WHITE_CAR)
    assert after[unchanged]["poses"] == next(a for a in actors if a["uuid"] == unchanged)["poses"]
    assert not np.array_equal(api.render(pose, stamp, "front_camera"), raw)
    # actors left out are removed, as neurad-studio does
    api.update_actors([a for a in actors if a["uuid"] != WHITE_CAR])
    assert WHITE_CAR not in {a["uuid"] for a in api.get_actors()}
    httpx.post(server.url + "/reset")
    assert np.array_equal(api.render(pose, stamp, "front_camera"), raw)


def test_pixels_equal_omnire_sim(server, served, serve_run, tmp_path):
    """A rig pose 1.5 m left of the recorded one at 1.25 s, the white car braking: the
    server's rig render equals omnire sim's frames for a camera path file of that pose."""
    t = 1.25
    rig = served.rig[12].copy()
    rig[:3, 3] += rig[:3, 1] * 1.5
    tables = {"actor": [{"track": WHITE_CAR, "stop_at": 1.0, "brake": 0.5}]}
    (tmp_path / "path.json").write_text(json.dumps({"seconds": [t], "rig_to_world": [rig.tolist()]}))
    (tmp_path / "s.toml").write_text(f'[camera]\npath = "file"\nfile = "path.json"\n\n[[actor]]\ntrack = "{WHITE_CAR}"\n'
                                     "stop_at = 1.0\nbrake = 0.5\n")
    out = tmp_path / "sim"
    subprocess.run([str(OMNIRE), "sim", str(serve_run), "--scenario", str(tmp_path / "s.toml"), "--output", str(out),
                    "--no-video", "--no-progress"], check=True, env=clean_env(), capture_output=True)
    client = httpx.Client(base_url=server.url, headers={"X-Omnire-Session": "pixels"}, timeout=300)
    assert client.post("/scenario", json=tables).status_code == 200
    r = client.post("/render_rig", json={"pose": rig.tolist(), "timestamp": served.start_us + 1_250_000,
                                         "image_format": "png"})
    assert r.status_code == 200, r.text
    images = r.json()["images"]
    assert set(images) == set(served.camera_names)
    for name, item in images.items():
        got = np.asarray(Image.open(io.BytesIO(base64.b64decode(item["data"]))))
        want = np.asarray(Image.open(out / name / "00000.png"))
        assert np.array_equal(got, want), name


def test_bad_requests_answer_json_and_the_server_goes_on(servers, served):
    server, guarded = servers
    client = httpx.Client(base_url=server.url, timeout=300)
    pose, stamp = _recorded_camera(served, 0, 3), int(served.frame_us[3])
    good = {"pose": pose, "timestamp": stamp, "camera_name": "front_camera", "image_format": "png"}
    nan_pose = [[float("nan")] * 4] + pose[1:]
    cases = [
        ("NaN pose", "POST", "/render_image", "pose", 400,
         {"content": json.dumps({**good, "pose": nan_pose}), "headers": {"content-type": "application/json"}}),
        ("unknown camera", "POST", "/render_image", "camera_name", 400, {"json": {**good, "camera_name": "rear"}}),
        ("10^6-pixel image", "POST", "/render_image", "width", 413, {"json": {**good, "width": 1000, "height": 1000}}),
        ("malformed JSON", "POST", "/render_image", "body", 400,
         {"content": b'{"pose": [[1, 0', "headers": {"content-type": "application/json"}}),
        ("time before the log", "POST", "/render_image", "timestamp", 400, {"json": {**good, "timestamp": stamp - 10**8}}),
        ("pose far outside the scene", "POST", "/render_rig", "pose", 400,
         {"json": {"pose": (np.eye(4) + np.pad([[0, 0, 0, 1e4]], ((0, 3), (0, 0)))).tolist(), "timestamp": stamp}}),
        ("missing field", "POST", "/render_image", "camera_name", 400, {"json": {"pose": pose, "timestamp": stamp}}),
        ("unknown actor", "POST", "/update_actors", "0.uuid", 400,
         {"json": [{"uuid": "nobody", "poses": [pose], "timestamps": [stamp], "dims": [1, 1, 1]}]}),
        ("bad scenario", "POST", "/scenario", "actor.0.stop_at", 400,
         {"json": {"actor": [{"track": WHITE_CAR, "stop_at": 99.0}]}}),
        ("insert from a file", "POST", "/scenario", "insert.0.run", 403,
         {"json": {"insert": [{"id": "x", "run": "/etc", "track": "t", "replace": WHITE_CAR}]}}),
        ("huge body", "POST", "/update_actors", "body", 413, {"content": b"[" + b"0," * (5 * 1024 * 1024) + b"0]"}),
        ("unknown endpoint", "GET", "/nothing", "path", 404, {}),
    ]
    for name, method, path, field, status, kw in cases:
        hostile_request(client, name, method, path, field, status, **kw)
        r = client.post("/render_image", json=good)  # the next good request still works
        assert r.status_code == 200 and r.headers["content-type"] == "image/png", name
    unauth = httpx.Client(base_url=guarded.url, timeout=300)
    hostile_request(unauth, "missing token", "POST", "/render_image", "Authorization", 401, json=good)
    hostile_request(unauth, "wrong token", "GET", "/alive", "Authorization", 401, headers={"Authorization": "Bearer nope"})
    r = unauth.post("/render_image", json=good, headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200


def test_sessions_do_not_share_edits(server, served):
    """Two clients render concurrently, one with the white car removed: each gets what it
    gets alone."""
    pose = served.rig[8].tolist()
    body = {"pose": pose, "timestamp": int(served.frame_us[8]), "cameras": ["front_camera"], "image_format": "png"}
    a = httpx.Client(base_url=server.url, headers={"X-Omnire-Session": "a"}, timeout=300)
    b = httpx.Client(base_url=server.url, headers={"X-Omnire-Session": "b"}, timeout=300)
    b.post("/scenario", json={"actor": [{"track": WHITE_CAR, "remove": True}]}).raise_for_status()
    alone = {k: c.post("/render_rig", json=body).json()["images"]["front_camera"]["data"] for k, c in (("a", a), ("b", b))}
    assert alone["a"] != alone["b"]
    got: dict[str, list] = {"a": [], "b": []}

    def run(key, c):
        for _ in range(3):
            got[key].append(c.post("/render_rig", json=body).json()["images"]["front_camera"]["data"])

    threads = [threading.Thread(target=run, args=(k, c)) for k, c in (("a", a), ("b", b))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert got["a"] == [alone["a"]] * 3 and got["b"] == [alone["b"]] * 3
    assert WHITE_CAR not in {x["id"] for x in b.post("/actors_at", json={"timestamp": body["timestamp"]}).json()}
    assert WHITE_CAR in {x["id"] for x in a.post("/actors_at", json={"timestamp": body["timestamp"]}).json()}
    b.post("/reset").raise_for_status()
    assert b.post("/render_rig", json=body).json()["images"]["front_camera"]["data"] == alone["a"]


def test_metadata(server, served):
    meta = httpx.get(server.url + "/metadata", timeout=300).json()
    assert [c["name"] for c in meta["cameras"]] == served.camera_names
    assert meta["time"]["start_us"] == served.start_us and meta["time"]["duration_s"] == pytest.approx(3.9, abs=0.01)
    car = next(a for a in meta["actors"] if a["id"] == WHITE_CAR)
    assert car["class"] == "Car" and car["category"] == "vehicle" and len(car["size"]) == 3
    assert meta["route"]["s"][-1] == pytest.approx(18.85, abs=0.05)


def test_non_loopback_needs_a_token(serve_run, tmp_path):
    r = subprocess.run([str(OMNIRE), "serve", str(serve_run), "--host", "0.0.0.0"], env=clean_env(), capture_output=True,
                       text=True, timeout=300)
    record("serve", "non-loopback without a token", exit=r.returncode,
           traceback=r.stderr if "Traceback" in r.stderr else None, wrong=r.returncode != 2)
    assert r.returncode == 2 and "needs a token" in r.stderr and "Traceback" not in r.stderr


def test_bench_serve_writes_its_table(serve_run, tmp_path):
    out = tmp_path / "bench.json"
    r = subprocess.run([str(OMNIRE), "bench", "serve", str(serve_run), "--requests", "2", "--clients", "1", "2",
                        "--width", "64", "--height", "36", "--threads", "1", "--output", str(out)],
                       env=clean_env(), capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    result = json.loads(out.read_text())
    rows = {(x["case"], x["clients"]): x for x in result["results"]}
    assert set(rows) == {("camera", 1), ("camera", 2), ("rig", 1), ("rig", 2)}
    assert rows[("rig", 2)]["cameras"] == 3 and rows[("camera", 2)]["requests"] == 4
    assert all(0 < x["p50_ms"] <= x["p95_ms"] for x in rows.values())
    # the server's Server-Timing split: rendering and encoding inside the client's latency
    assert all(0 < x["render_p50_ms"] and 0 <= x["encode_p50_ms"] and x["rest_p50_ms"] > 0 for x in rows.values())
    assert "| rig | 3 | 2 |" in r.stdout
