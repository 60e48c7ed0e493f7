"""What a benchmark ran on, so that numbers from different machines are not compared as if
they came from one: the CPU's model and vector extensions, and two short probes on the
benchmark's threads. Machines of one kind differ: this project's sessions measured one
code's training step (~350k Gaussians) at about 150 ms on one and about 180 ms on another,
whose fp32 matrix products ran 2.4x faster (130-140 GFLOP/s against 323 on 2 threads;
CHANGELOG.md, "Machines").
"""
from __future__ import annotations

import os
import platform
import time
from pathlib import Path


def _cpuinfo() -> tuple[str, set[str]]:
    """(model name, flags) from /proc/cpuinfo; without it (not Linux) the platform's
    processor string and no flags."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor(), set()
    model, flags = "", set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and not model:
            model = value.strip()
        elif key.strip() == "flags" and not flags:
            flags = set(value.split())
    return model, flags


def _best_seconds(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def machine_info(threads: int) -> dict:
    """CPU model, logical cores, AVX2 / AVX-512, torch version, and the best of a few runs of
    a 64 MB tensor copy (GB/s read + written) and a 1024^3 fp32 matrix product (GFLOP/s), on
    ``threads`` torch threads (0: torch's current number; restored afterwards). About a
    quarter of a second."""
    import torch

    model, flags = _cpuinfo()
    before = torch.get_num_threads()
    threads = threads if threads > 0 else before
    torch.set_num_threads(threads)
    try:
        src = torch.ones(16 * 1024 * 1024)  # 64 MB of float32: past the caches of a laptop or a server core
        dst = torch.empty_like(src)
        copy_s = _best_seconds(lambda: dst.copy_(src), 5)
        a = torch.rand(1024, 1024)
        mm_s = _best_seconds(lambda: a @ a, 5)
    finally:
        torch.set_num_threads(before)
    return {
        "cpu": model or "unknown",
        "logical_cores": os.cpu_count(),
        "avx2": "avx2" in flags,
        "avx512f": "avx512f" in flags,
        "torch": torch.__version__,
        "threads": threads,
        "copy_gb_s": round(2 * src.numel() * 4 / copy_s / 1e9, 1),
        "matmul_gflop_s": round(2 * 1024**3 / mm_s / 1e9, 1),
    }


def machine_line(info: dict) -> str:
    """One line for a table's caption."""
    ext = "AVX-512" if info.get("avx512f") else "AVX2" if info.get("avx2") else "no AVX2"
    return (f"{info['cpu']} ({info['logical_cores']} logical cores, {ext}), torch {info['torch']}: "
            f"{info['copy_gb_s']} GB/s copy, {info['matmul_gflop_s']} GFLOP/s fp32 matmul on {info['threads']} thread(s)")
