"""When a PandaSet cuboid holds its actor: at the frame's timestamp, or when the sensor saw it.

The reader takes each frame's cuboids as the actors' poses at the frame's LiDAR timestamp
(the end of the sweep, docs/lidar.md "PandaSet"). For every vehicle moving faster than
``--min-speed`` (speed from its boxes one frame before and after) with at least 30 Pandar64
returns within 1 m (0.5 m sideways) of its box, this prints the mean offset of those
returns from the box centre along the velocity, beside ``v dt``: the offset a box at the
frame's timestamp would give (speed x (mean time of the returns - frame timestamp), the
returns being 0.05-0.1 s older). Offsets near ``v dt`` mean frame-time boxes; offsets
scattered around 0 and uncorrelated with it mean boxes drawn where the sensor saw the actor.

Usage (the sweeps and their timestamps of ``--lidar``, the cuboids of ``--cuboids``, files
named by the same frame numbers)::

    .venv/bin/python dataparsers/pandaset/tools/box_timing.py \
        [--lidar ../shared/data/pandaset/002-full-lidar/lidar] [--cuboids ../shared/data/pandaset/002/annotations/cuboids]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[3]
SHARED = REPO.parent / "shared" / "data" / "pandaset"


def moving_box_offsets(lidar: Path, cuboids: Path, min_speed: float) -> pd.DataFrame:
    """One row per moving vehicle and frame: frame, speed, offset along the velocity of its
    returns' centroid from the box centre (m), ``v_dt`` (m) and the number of returns."""
    stamps = json.loads((lidar / "timestamps.json").read_text())
    frames = sorted(int(p.name.split(".")[0]) for p in lidar.glob("*.pkl.gz"))
    first = 0 if len(stamps) > frames[-1] else frames[0]  # the whole log's stamps, or the folder's from its first
    rows = []
    for f in frames:
        names = [cuboids / f"{g:02d}.pkl.gz" for g in (f - 1, f, f + 1)]
        if f - 1 not in frames or f + 1 not in frames or not all(n.exists() for n in names):
            continue
        before, boxes, after = (pd.read_pickle(n).drop_duplicates("uuid").set_index("uuid") for n in names)
        sweep = pd.read_pickle(lidar / f"{f:02d}.pkl.gz")
        sweep = sweep[sweep.d == 0]  # the Pandar64
        xyz, t = sweep[["x", "y", "z"]].to_numpy(), sweep.t.to_numpy()
        dt_frames = stamps[f + 1 - first] - stamps[f - 1 - first]
        for uuid, box in boxes.iterrows():
            if uuid not in before.index or uuid not in after.index or "Car" not in box.label and "Truck" not in box.label:
                continue
            velocity = np.array([after.at[uuid, "position.x"] - before.at[uuid, "position.x"],
                                 after.at[uuid, "position.y"] - before.at[uuid, "position.y"]]) / dt_frames
            speed = float(np.linalg.norm(velocity))
            if speed < min_speed:
                continue
            d = xyz - np.array([box["position.x"], box["position.y"], box["position.z"]])
            c, s = np.cos(box["yaw"]), np.sin(box["yaw"])
            along, side = d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c
            near = ((np.abs(along) <= box["dimensions.y"] / 2 + 1.0) & (np.abs(side) <= box["dimensions.x"] / 2 + 0.5)
                    & (np.abs(d[:, 2]) <= box["dimensions.z"] / 2))
            if near.sum() < 30:
                continue
            offset = float((d[near, :2] @ (velocity / speed)).mean())
            rows.append((f, speed, offset, speed * (t[near].mean() - stamps[f - first]), int(near.sum())))
    return pd.DataFrame(rows, columns=["frame", "speed", "offset", "v_dt", "returns"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lidar", type=Path, default=SHARED / "002-full-lidar" / "lidar")
    parser.add_argument("--cuboids", type=Path, default=SHARED / "002" / "annotations" / "cuboids")
    parser.add_argument("--min-speed", type=float, default=2.0, help="m/s")
    args = parser.parse_args()
    table = moving_box_offsets(args.lidar, args.cuboids, args.min_speed)
    print(f"{len(table)} moving vehicles x frames")
    print(table[["offset", "v_dt"]].describe().round(3).to_string())
    print(f"median |offset| {table.offset.abs().median():.3f} m; correlation of offset and v_dt "
          f"{np.corrcoef(table.offset, table.v_dt)[0, 1]:.2f}")


if __name__ == "__main__":
    main()
