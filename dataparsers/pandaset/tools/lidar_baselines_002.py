"""Print the two LiDAR baselines' figures on the complete PandaSet sweeps of log 002.

The held-out sweeps are the every-10th frames of frames 40-79 (``holdout_split``, as the
cameras); both baselines are built from the other sweeps (``omnire.api.baseline_metrics``).
The shared copy keeps its camera/annotations/meta links as text files, so the scene is
assembled in a temporary directory of links.

Usage (from the repo top)::

    .venv/bin/python dataparsers/pandaset/tools/lidar_baselines_002.py [--shared ../shared/data/pandaset]
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from omnire.api import baseline_metrics
from omnire_pandaset import PandasetConfig

REPO = Path(__file__).resolve().parents[3]
KEYS = ("median_abs_range_error", "mean_abs_range_error", "mean_relative_range_error", "range_coverage",
        "intensity_rmse", "drop_accuracy", "drop_f1", "chamfer", "vehicle_median_abs_range_error",
        "vehicle_mean_abs_range_error", "vehicle_returns", "human_median_abs_range_error",
        "human_mean_abs_range_error", "human_returns", "returns", "rays")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data" / "pandaset")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for sub in ("camera", "annotations", "meta"):
            (root / sub).symlink_to((args.shared / "002" / sub).resolve())
        (root / "lidar").symlink_to((args.shared / "002-full-lidar" / "lidar").resolve())
        scene = PandasetConfig(data=root, cameras=("front_camera",), start_frame=40, end_frame=80,
                               lidar_sensors=(0,)).setup().parse()
        result = baseline_metrics(scene, scene.test_frames, scene.train_frames)
    print(f"held-out frames {[int(f) + 40 for f in scene.test_frames]}, training sweeps "
          f"{len([f for f in scene.train_frames if scene.lidar.points[f] is not None])}")
    print(f"{'figure':34s} " + " ".join(f"{name:>14s}" for name in result))
    for key in KEYS:
        print(f"{key:34s} " + " ".join(f"{result[name][key]:14.4f}" for name in result))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
