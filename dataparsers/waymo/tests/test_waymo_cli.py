"""End to end through the CLI: ``omnire synth --format waymo`` writes a segment that
``omnire train 3dgs waymo`` trains on (subprocesses, as a user runs them)."""
from __future__ import annotations

import json

import numpy as np

from omnire_waymo import WaymoConfig


def test_synth_format_waymo_then_train(omnire_cli, tmp_path, monkeypatch):
    scene = tmp_path / "scene"
    omnire_cli("synth", "urban", str(scene), "--frames", "4", "--width", "48", "--height", "32",
               "--lidar-beams", "8", "--format", "waymo")
    (segment,) = scene.iterdir()  # one file, named like a Waymo segment
    assert segment.name == "segment-omnire_synthetic_urban_seed0_with_camera_labels.tfrecord"
    s = WaymoConfig(data=scene, image_dir=tmp_path / "img", scale=1.0).setup().parse()
    assert s.num_frames == 4 and (s.cameras[0].width, s.cameras[0].height) == (48, 32)
    assert all(p is not None and len(p) > 100 for p in s.lidar.points) and s.tracks
    assert s.attribution.startswith("Synthetic scene")

    out = tmp_path / "runs"
    monkeypatch.setenv("OMNIRE_WAYMO_IMAGE_DIR", str(tmp_path / "img_train"))  # inherited by the subprocess
    omnire_cli("train", "3dgs", "waymo", "--data", str(scene), "--trainer.max-steps", "3", "--trainer.no-progress",
               "--method.rasterizer", "torch", "--method.nodes.background.max-lidar-points", "2000",
               "--method.nodes.background.num-far-points", "200", "--trainer.output-dir", str(out))
    (run,) = out.iterdir()
    assert (run / "run.json").is_file()
    assert any((tmp_path / "img_train").glob("*/*.jpg"))  # images went to the given cache, not the dataset
    assert list(scene.iterdir()) == [segment]
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    assert rows and all(np.isfinite(v) for r in rows for v in r.values() if isinstance(v, float))
