"""gsplat (CUDA) rasterizer plugin for omnire (registry name ``gsplat``)."""
from __future__ import annotations

import functools


@functools.lru_cache(maxsize=None)
def _gsplat_import_error() -> str:
    try:
        import gsplat  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import failure means unavailable
        return f"gsplat cannot be imported ({type(exc).__name__}: {exc}); pip install omnire-rasterizer-gsplat[cuda]"
    return ""


def available(device=None) -> tuple[bool, str]:
    """``(True, "")`` only on a CUDA device with CUDA present and gsplat importable."""
    import torch

    if device is not None and torch.device(device).type != "cuda":
        return False, f"needs a CUDA device (asked for {torch.device(device)})"
    if not torch.cuda.is_available():
        return False, "CUDA is not available (torch.cuda.is_available() is False)"
    err = _gsplat_import_error()
    return (not err), err
