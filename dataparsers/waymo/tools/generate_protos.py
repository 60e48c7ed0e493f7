"""Regenerate ``omnire_waymo/wod/*_pb2.py`` from the shipped ``omnire_waymo/wod/*.proto``.

The ``.proto`` files are the Waymo Open Dataset v1 message definitions (Apache-2.0, from the
public waymo-open-dataset repository) with one change: their ``import`` lines point into this
package (``omnire_waymo/wod/...``) so the generated modules import each other as
``omnire_waymo.wod.*_pb2`` and never collide with an installed ``waymo_open_dataset``.
Message names and field numbers are untouched (wire-compatible with the dataset).

    # refresh the .proto copies from a Waymo protos folder (optional), then compile
    python tools/generate_protos.py --from ../shared/data/waymo/protos
    python tools/generate_protos.py

Needs ``grpcio-tools==1.62.3`` (protoc 25): its output runs on the protobuf 4.25.x runtime
that ``pyproject.toml`` pins (newer protoc emits code that refuses a 4.x runtime).
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]  # dataparsers/waymo
OUT = HERE / "omnire_waymo" / "wod"
# upstream path (relative to the protos root) -> shipped file name
FILES = {
    "waymo_open_dataset/dataset.proto": "dataset.proto",
    "waymo_open_dataset/label.proto": "label.proto",
    "waymo_open_dataset/protos/keypoint.proto": "keypoint.proto",
    "waymo_open_dataset/protos/vector.proto": "vector.proto",
    "waymo_open_dataset/protos/map.proto": "map.proto",
}
NOTE = "// Modified for omnire: import paths point into the omnire_waymo package (tools/generate_protos.py).\n"


def _rewrite(text: str) -> str:
    def repl(m: re.Match) -> str:
        name = FILES.get(m.group(1))
        if name is None:
            raise SystemExit(f"unexpected import {m.group(1)!r}; add it to FILES")
        return f'import "omnire_waymo/wod/{name}";'

    text = re.sub(r'import "([^"]+)";', repl, text)
    if NOTE not in text:
        text = text.replace("syntax = ", NOTE + "\nsyntax = ", 1)
    return text


def refresh(src: Path) -> None:
    for rel, name in FILES.items():
        (OUT / name).write_text(_rewrite((src / rel).read_text()))


def compile_protos(out_root: Path = HERE) -> None:
    """``*_pb2.py`` for the shipped ``.proto`` files under ``out_root/omnire_waymo/wod``."""
    from grpc_tools import protoc

    args = ["protoc", f"-I{HERE}", f"--python_out={out_root}"] + [str(OUT / n) for n in FILES.values()]
    if protoc.main(args) != 0:
        raise SystemExit("protoc failed")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--from", dest="src", type=Path, help="Waymo protos root holding waymo_open_dataset/")
    a = p.parse_args(argv)
    if a.src is not None:
        refresh(a.src)
    compile_protos()
    return 0


if __name__ == "__main__":
    sys.exit(main())
