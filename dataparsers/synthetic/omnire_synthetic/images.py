"""Image writing through OpenImageIO (JPEG colour, 8-bit PNG masks)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio


def _write(path: Path, arr: np.ndarray, compression: str | None = None) -> None:
    arr = np.ascontiguousarray(arr)
    h, w, c = arr.shape
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"{path}: cannot create image writer ({oiio.geterror()})")
    spec = oiio.ImageSpec(w, h, c, "uint8")
    if compression:
        spec.attribute("Compression", compression)
    if not out.open(str(path), spec) or not out.write_image(arr):
        err = out.geterror()
        out.close()
        raise OSError(f"{path}: write failed ({err})")
    out.close()


def write_rgb(path: Path, img: np.ndarray, quality: int = 95) -> None:
    """img (H, W, 3) float in [0, 1]."""
    _write(path, (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), f"jpeg:{int(quality)}")


def write_mask(path: Path, mask: np.ndarray) -> None:
    """mask (H, W) bool -> 0/255 PNG."""
    _write(path, (mask.astype(np.uint8) * 255)[..., None])


def read_image(path: Path) -> np.ndarray:
    """(H, W, C) uint8."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"{path}: cannot open image ({oiio.geterror()})")
    try:
        spec = inp.spec()
        return inp.read_image(0, 0, 0, spec.nchannels, "uint8")
    finally:
        inp.close()
