"""Writing images (PNG via OpenImageIO, atomically)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import torch

from omnire.io.atomic import current_umask


def write_png(path: str | Path, image: torch.Tensor | np.ndarray, bits: int = 8) -> None:
    """Write (H,W,C) values in [0,1] (8-bit) or raw values clipped to 0..65535 (16-bit)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = image.detach().cpu().numpy() if torch.is_tensor(image) else np.asarray(image)
    if bits == 8:
        data, fmt = (np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8), oiio.UINT8
    else:
        data, fmt = np.clip(arr, 0, 65535).astype(np.uint16), oiio.UINT16
    h, w, c = data.shape
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".png")
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, oiio.ImageSpec(w, h, c, fmt)):
            raise OSError(f"{path}: cannot write image ({oiio.geterror()})")
        ok = out.write_image(np.ascontiguousarray(data))
        ok = out.close() and ok  # close flushes: a full disk shows here
        if not ok or os.path.getsize(tmp) == 0:
            raise OSError(f"{path}: writing failed ({oiio.geterror() or 'no space left or write error'})")
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
