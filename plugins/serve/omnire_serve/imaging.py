"""Rendered images as bytes: 8-bit quantisation (as ``omnire sim`` writes its PNGs), PNG /
JPEG encoding and neurad-studio's "raw" format (a base64 text of a ``torch.save``d uint8
tensor)."""
from __future__ import annotations

import base64
import io

import numpy as np
import torch
from PIL import Image

FORMATS = ("raw", "png", "jpg", "jpeg")


def to_uint8(rgb: "torch.Tensor | np.ndarray") -> np.ndarray:
    """(H, W, 3) values in [0, 1] -> (H, W, 3) uint8, rounded as omnire.io.images.write_png does."""
    arr = rgb.detach().cpu().numpy() if torch.is_tensor(rgb) else np.asarray(rgb)
    return (np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8)


def encode(image: np.ndarray, fmt: str) -> tuple[bytes, str]:
    """(bytes, media type) of a (H, W, 3) uint8 image in ``fmt`` (one of :data:`FORMATS`)."""
    if fmt == "raw":
        buf = io.BytesIO()
        torch.save(torch.from_numpy(np.ascontiguousarray(image)), buf)
        return base64.b64encode(buf.getvalue()), "text/plain"
    buf = io.BytesIO()
    if fmt == "png":
        Image.fromarray(image).save(buf, format="PNG", compress_level=1)
        return buf.getvalue(), "image/png"
    Image.fromarray(image).save(buf, format="JPEG", quality=90)
    return buf.getvalue(), "image/jpeg"


def decode(data: bytes, fmt: str) -> np.ndarray:
    """The inverse of :func:`encode`: (H, W, 3) uint8."""
    if fmt == "raw":
        return torch.load(io.BytesIO(base64.b64decode(data)), weights_only=True).numpy()
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
