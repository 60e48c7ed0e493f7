"""The cpu rasterizer's C++ extensions, built at first use and cached by
:class:`omnire.native.NativeExtension`: the camera kernels (csrc/raster.cpp, csrc/ssim.cpp,
about a minute on 2 cores) and, apart so that each builds only when used, the LiDAR
compositing (csrc/lidar.cpp, about 20 seconds)."""
from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Optional

from omnire.api import NativeExtension, build_error_line  # noqa: F401 - re-exported for callers

SOURCES = [Path(__file__).parent / "csrc" / name for name in ("raster.cpp", "ssim.cpp")]
# Portable flags: AVX2 + FMA (not -march=native, which ties the .so to one machine).
# -ffp-contract=off keeps forward and backward bit-identical in their skip/stop decisions.
CFLAGS = ("-O3", "-mavx2", "-mfma", "-fopenmp", "-ffp-contract=off", "-std=c++17")
LDFLAGS = ("-fopenmp",)

EXTENSION = NativeExtension("omnire_raster_cpu", SOURCES, CFLAGS, LDFLAGS, cpu_flags=("avx2", "fma"),
                            purpose="omnire cpu rasterizer")


LIDAR_EXTENSION = NativeExtension("omnire_lidar_cpu", [Path(__file__).parent / "csrc" / "lidar.cpp"], CFLAGS,
                                  LDFLAGS, cpu_flags=("avx2", "fma"), purpose="omnire cpu LiDAR rasterizer")


def build_directory() -> Path:
    return EXTENSION.build_directory()


def load_extension() -> tuple[Optional[ModuleType], str]:
    """Return ``(module, "")`` or ``(None, reason)``; builds at most once per process."""
    return EXTENSION.load()


def load_lidar_extension() -> tuple[Optional[ModuleType], str]:
    """Return ``(module, "")`` or ``(None, reason)`` for the LiDAR extension."""
    return LIDAR_EXTENSION.load()


def extension() -> ModuleType:
    """The loaded extension; a RuntimeError saying why when it is unavailable."""
    return EXTENSION.module()


def lidar_extension() -> ModuleType:
    """The loaded LiDAR extension; a RuntimeError saying why when it is unavailable."""
    return LIDAR_EXTENSION.module()
