"""Cut the shared PandaSet log 002 into the small demo scene shipped with omnire.

Writes ``data/demo/pandaset_002/`` (repo top) in PandaSet's own layout, so the same
``pandaset`` dataparser reads it:

- frames 40..79 (the part where the ego moves, docs/conventions.md "The demo log"), renumbered 00..39 so
  the cut is a regular PandaSet sequence (files start at 00, per-frame json lists start at
  the first file); the original numbers go to ``meta/source_frames.json``, which the parser
  reports as ``SceneData.source_frames``;
- the three front cameras, images resized 960x540 -> 480x270 (OpenImageIO, Lanczos-style
  filtered resize) and re-encoded as JPEG quality 90; intrinsics scaled by the same ratio;
- LiDAR thinned to a fixed random subset of 8000 points per frame (seeded by the original
  frame number), x/y/z/i stored as float32, t kept float64 (absolute seconds need it),
  d (sensor id) as int8; LiDAR gaps of the source (56-58, 71) stay gaps;
- cuboids copied unchanged; semseg dropped; poses/timestamps/gps sliced.

The output is deterministic: same inputs give byte-identical files (gzip mtime fixed to 0).

Usage (from the repo top)::

    .venv/bin/python dataparsers/pandaset/tools/make_demo_cut.py \
        [--src ../shared/data/pandaset/002] [--out data/demo/pandaset_002]
"""
from __future__ import annotations

import argparse
import gzip
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pandas as pd

from omnire_pandaset.dataparser import load_frame_table

REPO = Path(__file__).resolve().parents[3]
CAMERAS = ("front_camera", "front_left_camera", "front_right_camera")

README = """\
# PandaSet 002, frames 40-79 — omnire demo scene

A small cut of a real urban driving log (San Francisco, daytime, 10 Hz) in PandaSet's own
on-disk layout; the `pandaset` dataparser reads it directly:

    omnire train <method> pandaset --data data/demo/pandaset_002

## Licence and attribution
PandaSet is published by Scale AI and Hesai under CC BY 4.0 together with the PandaSet
Dataset Terms of Use (commercial use allowed, attribution required, no use to identify
persons). Anything that ships or derives from these files must carry this attribution:
"PandaSet: Advanced Sensor Suite Dataset for Autonomous Driving", Xiao et al., ITSC 2021,
CC BY 4.0. Provenance: the test fixture test/data/002 of the public pandaset-devkit
repository at commit c20729732f522c1bce81cb85a13bb02c96344bb4, as stored in
`../shared/data/pandaset/002` (itself 960x540, LiDAR thinned to 12%; see its README).

## What changed against that source
- Frames 40..79 only (the ego moves there; it barely moves over frames 0-30), renumbered
  00..39. `meta/source_frames.json` lists the original numbers (40..79); the dataparser
  reports them as `source_frames`. `--start-frame/--end-frame` index the files here (0..39).
- Only the three front cameras; images resized to {width}x{height} and re-encoded as JPEG
  quality {quality}; `intrinsics.json` scaled by the same ratio.
- LiDAR thinned to a fixed random {points} points per frame (seed = original frame number),
  columns x, y, z, i as float32, t as float64, d as int8 (0 = Pandar64, 1 = PandarGT).
  Source LiDAR frames 56, 57, 58 and 71 are missing (files 16, 17, 18 and 31 here): a real
  gap that readers must handle.
- Cuboid annotations copied unchanged; LiDAR semseg dropped.

## Regenerate
From the repository top (needs `../shared/data/pandaset/002`; output is byte-identical):

    .venv/bin/python dataparsers/pandaset/tools/make_demo_cut.py
"""


def write_json(path: Path, data: object) -> None:
    path.write_text(json.dumps(data, indent=1) + "\n")


def write_pickle_gz(path: Path, obj: object) -> None:
    # mtime=0 and no file name in the header: identical bytes on every run.
    with open(path, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as gz:
        gz.write(pickle.dumps(obj, protocol=4))


def resize_jpeg(src: Path, dst: Path, width: int, height: int, quality: int) -> None:
    buf = oiio.ImageBuf(str(src))
    out = oiio.ImageBufAlgo.resize(buf, roi=oiio.ROI(0, width, 0, height, 0, 1, 0, buf.nchannels))
    if out.has_error:
        raise RuntimeError(f"{src}: resize failed: {out.geterror()}")
    out.specmod().attribute("Compression", f"jpeg:{quality}")
    out.set_write_format(oiio.UINT8)
    if not out.write(str(dst)):
        raise RuntimeError(f"{dst}: write failed: {out.geterror()}")


def thin_lidar(table: pd.DataFrame, points: int, seed: int) -> pd.DataFrame:
    """(N rows) -> (min(N, points) rows), fixed random subset in the original row order."""
    if len(table) > points:
        rng = np.random.default_rng(seed)
        table = table.iloc[np.sort(rng.choice(len(table), points, replace=False))]
    thinned = pd.DataFrame(
        {
            "x": table["x"].to_numpy(np.float32),
            "y": table["y"].to_numpy(np.float32),
            "z": table["z"].to_numpy(np.float32),
            "i": table["i"].to_numpy(np.float32),
            "t": table["t"].to_numpy(np.float64),
            "d": table["d"].to_numpy(np.int8),
        },
        index=pd.Index(table.index.to_numpy(np.int64), name=table.index.name),
    )
    # Plain object-dtype column labels, as in PandaSet's own pickles: pandas >= 3 would pickle
    # string labels as a StringArray, which the restricted unpickler (rightly) refuses.
    thinned.columns = pd.Index(list(thinned.columns), dtype=object)
    return thinned


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--src", type=Path, default=REPO.parent / "shared/data/pandaset/002")
    ap.add_argument("--out", type=Path, default=REPO / "data/demo/pandaset_002")
    ap.add_argument("--first", type=int, default=40, help="first source frame")
    ap.add_argument("--last", type=int, default=79, help="last source frame (inclusive)")
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=270)
    ap.add_argument("--quality", type=int, default=90, help="JPEG quality")
    ap.add_argument("--lidar-points", type=int, default=8000, help="points kept per LiDAR frame")
    args = ap.parse_args()
    src, out = args.src, args.out
    if not (src / "lidar" / "poses.json").is_file():
        raise SystemExit(f"{src}: not a PandaSet sequence (no lidar/poses.json)")
    frames = list(range(args.first, args.last + 1))
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)

    def sliced(rel: str) -> list:
        data = json.loads((src / rel).read_text())
        return [data[f] for f in frames]

    for cam in CAMERAS:
        cdir = out / "camera" / cam
        cdir.mkdir(parents=True)
        spec = oiio.ImageInput.open(str(src / "camera" / cam / f"{frames[0]:02d}.jpg")).spec()
        sx, sy = args.width / spec.width, args.height / spec.height
        k = json.loads((src / "camera" / cam / "intrinsics.json").read_text())
        write_json(cdir / "intrinsics.json", {"fx": k["fx"] * sx, "fy": k["fy"] * sy, "cx": k["cx"] * sx, "cy": k["cy"] * sy})
        write_json(cdir / "poses.json", sliced(f"camera/{cam}/poses.json"))
        write_json(cdir / "timestamps.json", sliced(f"camera/{cam}/timestamps.json"))
        for i, f in enumerate(frames):
            resize_jpeg(src / "camera" / cam / f"{f:02d}.jpg", cdir / f"{i:02d}.jpg", args.width, args.height, args.quality)

    ldir = out / "lidar"
    ldir.mkdir()
    write_json(ldir / "poses.json", sliced("lidar/poses.json"))
    write_json(ldir / "timestamps.json", sliced("lidar/timestamps.json"))
    counts = []
    for i, f in enumerate(frames):
        path = src / "lidar" / f"{f:02d}.pkl.gz"
        if not path.is_file():
            continue  # keep the source's gap
        table = thin_lidar(load_frame_table(path), args.lidar_points, seed=f)
        write_pickle_gz(ldir / f"{i:02d}.pkl.gz", table)
        counts.append(len(table))

    bdir = out / "annotations" / "cuboids"
    bdir.mkdir(parents=True)
    for i, f in enumerate(frames):
        shutil.copyfile(src / "annotations" / "cuboids" / f"{f:02d}.pkl.gz", bdir / f"{i:02d}.pkl.gz")

    mdir = out / "meta"
    mdir.mkdir()
    write_json(mdir / "timestamps.json", sliced("meta/timestamps.json"))
    write_json(mdir / "gps.json", sliced("meta/gps.json"))
    write_json(mdir / "source_frames.json", frames)
    (out / "README.md").write_text(
        README.format(width=args.width, height=args.height, quality=args.quality, points=args.lidar_points)
    )
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"{out}: {len(frames)} frames, {len(counts)} LiDAR sweeps (~{int(np.mean(counts))} points), {size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
