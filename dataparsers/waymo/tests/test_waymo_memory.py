"""Streaming: reading a large segment does not hold it in memory.

A ~200 MiB Waymo-like segment (omnire_waymo.bench.generate_segment: ~60 frames of five JPEG
cameras, five LiDARs with two returns and TOP pixel poses, 60 boxes) is read with LiDAR in a
fresh process; that process's peak RSS above its post-import state must stay well below the
file size and within a fixed budget beyond what the reader returns. ``omnire bench
waymo-read`` does the same at 1 GiB (numbers in the package README).
"""
from __future__ import annotations

from omnire_waymo.bench import generate_segment, measure_in_subprocess

FILE_MB = 200
BUDGET_MB = 100
"""Peak growth beyond the returned arrays: one frame's payload, decoded range images and
their points in float64 (measured ~55 MiB), with headroom."""


def test_peak_memory_does_not_grow_with_the_file(tmp_path):
    seg = tmp_path / "big.tfrecord"
    info = generate_segment(seg, FILE_MB * 2**20)
    assert info["bytes"] >= FILE_MB * 2**20 and info["frames"] > 40
    r = measure_in_subprocess(seg, tmp_path / "img", load_lidar=True, max_points=5000)
    assert r["frames"] == info["frames"] and r["lidar_points"] == 5000 * info["frames"]
    assert r["peak_growth_mb"] < FILE_MB / 2, r
    assert r["peak_growth_mb"] - r["retained_mb"] < BUDGET_MB, r
