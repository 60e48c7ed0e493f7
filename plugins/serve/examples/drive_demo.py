"""Drive the demo scene closed-loop and write each episode's metrics.json and episode.mp4.

    python plugins/serve/examples/drive_demo.py RUN OUTPUT              # in this process
    python plugins/serve/examples/drive_demo.py RUN OUTPUT --url http://127.0.0.1:8000   # through omnire serve RUN

Three episodes (docs/closed_loop.md): ``lane_keeping`` (the recorded traffic, a lane keeper
at 7 m/s to the route's end), ``braking_ignored`` (the white car ahead brakes hard; the lane
keeper ignores it and collides) and ``braking`` (the same scenario, braking for the car ahead).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from omnire_serve.controllers import LaneKeeper
from omnire_serve.env import DrivingEnv, EnvConfig
from omnire_serve.rollout import rollout, write_report

WHITE_CAR = "8ac00bad-822c-4040-b9a2-31424dbcd486"
BRAKING = {"actor": [{"track": WHITE_CAR, "stop_at": 0.4, "brake": 0.4}]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("output", type=Path)
    parser.add_argument("--url", help="an omnire serve server of RUN (default: render in this process)")
    parser.add_argument("--token", help="the server's token, if it asks for one")
    args = parser.parse_args()
    if args.url:
        from omnire_serve.client import OmnireClient
        from omnire_serve.transport import HttpTransport

        transport = HttpTransport(OmnireClient(args.url, token=args.token))
    else:
        from omnire.api import Reconstruction
        from omnire.plugins import load_plugins
        from omnire_serve.served import ServedScene
        from omnire_serve.transport import LocalTransport

        plugins = load_plugins()
        transport = LocalTransport(ServedScene(Reconstruction.from_run(args.run, plugins), plugins))
    env = DrivingEnv(transport, EnvConfig())
    episodes = {"lane_keeping": (LaneKeeper(speed=7.0), None),
                "braking_ignored": (LaneKeeper(speed=7.0), BRAKING),
                "braking": (LaneKeeper(speed=7.0, brake_for_lead=True), BRAKING)}
    for name, (driver, scenario) in episodes.items():
        frames, infos = rollout(env, driver, scenario)
        metrics = write_report(args.output / name, env, frames, infos)
        print(name, json.dumps({k: metrics[k] for k in ("end", "collision", "min_time_to_collision", "score")}))


if __name__ == "__main__":
    main()
