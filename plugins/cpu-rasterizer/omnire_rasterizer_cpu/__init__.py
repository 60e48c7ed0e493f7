"""Native CPU rasterizer plugin for omnire (registry name ``cpu``)."""
from omnire_rasterizer_cpu._build import load_extension

__all__ = ["CpuRasterizer", "available", "load_extension"]


def available(device=None) -> tuple[bool, str]:
    """``(True, "")`` when ``device`` is a CPU and the C++ extension builds/loads."""
    import torch

    if device is not None and torch.device(device).type != "cpu":
        return False, f"runs on CPU only (asked for {torch.device(device)})"
    mod, reason = load_extension()
    return (mod is not None), reason


def __getattr__(name):
    if name == "CpuRasterizer":
        from omnire_rasterizer_cpu.rasterizer import CpuRasterizer

        return CpuRasterizer
    raise AttributeError(name)
