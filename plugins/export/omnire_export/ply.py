"""The standard 3DGS PLY layout, written in a stream.

One ``vertex`` element, every property ``float`` (float32), binary little-endian, in the
order the original 3DGS code writes and common splat viewers read::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..44  opacity  scale_0..2  rot_0..3

- ``f_dc_c``: the DC spherical-harmonic coefficient of colour channel c (``sh0[:, 0, c]``).
- ``f_rest_i``: the 15 higher coefficients (bands 1-3) channel-major:
  ``f_rest_{c * 15 + k} = shN[:, k, c]``; bands a node does not have, or that the trained
  model does not use yet, are written as zeros.
- ``opacity``: the logit (raw parameter); ``scale_j``: log standard deviations (raw);
  ``rot_0..3``: the rotation quaternion w x y z (raw, not normalised; a zero quaternion,
  which the rasterizers treat as the identity, is written as 1 0 0 0 so that viewers that
  normalise do not divide by zero). Normals are zero.
- ``lidar_intensity lidar_ray_drop`` (:data:`LIDAR_PROPERTIES`), after those, only for a
  scene trained with LiDAR rendering (``--method.lidar.enabled``): the learned LiDAR
  features, raw logits like the opacity (sigmoid gives the intensity in [0, 1] and the
  ray-drop probability; omnire/lidarmodel.py). Viewers skip properties they do not know.

Files are written to a temporary file beside the target and renamed when complete. The
vertex count is patched into the header at the end, so the rows can be produced chunk by
chunk without knowing their number in advance (the header keeps its length: a padding
comment absorbs the difference).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np

SH_REST = 15
"""Higher SH coefficients per channel in the layout (degree 3: 16 - 1)."""

PLY_PROPERTIES: tuple[str, ...] = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    *(f"f_rest_{i}" for i in range(3 * SH_REST)),
    "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)
"""Vertex property names in file order (62)."""

LIDAR_PROPERTIES: tuple[str, ...] = ("lidar_intensity", "lidar_ray_drop")
"""Properties appended for scenes with learned LiDAR features (raw logits)."""

ROW_FLOATS = len(PLY_PROPERTIES)
ROW_DTYPE = np.dtype("<f4")
_COUNT_WIDTH = 20  # digits reserved for the vertex count before it is known


def ply_header(count: int, comments: tuple[str, ...] = (), pad: int = 0, lidar: bool = False) -> bytes:
    """The header for ``count`` vertices; ``pad`` spaces are appended to a padding comment;
    ``lidar``: with :data:`LIDAR_PROPERTIES`."""
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {count}")
    lines += [f"property float {name}" for name in PLY_PROPERTIES + (LIDAR_PROPERTIES if lidar else ())]
    lines.append("comment pad" + " " * pad)
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def pack_rows(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
              sh0: np.ndarray, shN: np.ndarray, sh_degree: int, lidar: Optional[np.ndarray] = None) -> np.ndarray:
    """Raw Gaussian parameters -> (n, 62) little-endian float32 PLY rows ((n, 64) with
    ``lidar``).

    Args:
        means (n, 3), quats (n, 4) wxyz, scales (n, 3) log, opacities (n,) logits,
        sh0 (n, 1, 3), shN (n, K-1, 3) with K <= 16.
        sh_degree: SH bands kept (0..3); higher coefficients are written as zeros.
        lidar: (n, 2) LiDAR feature logits, or None.
    """
    n = len(means)
    rows = np.zeros((n, ROW_FLOATS + (len(LIDAR_PROPERTIES) if lidar is not None else 0)), dtype=ROW_DTYPE)
    rows[:, 0:3] = means
    # normals (3:6) stay zero
    rows[:, 6:9] = sh0.reshape(n, 3)
    keep = min(shN.shape[1], (sh_degree + 1) ** 2 - 1)
    if keep > 0:
        rest = rows[:, 9:9 + 3 * SH_REST].reshape(n, 3, SH_REST)  # channel-major view
        rest[:, :, :keep] = np.transpose(shN[:, :keep, :], (0, 2, 1))
    o = 9 + 3 * SH_REST
    rows[:, o] = opacities.reshape(n)
    rows[:, o + 1:o + 4] = scales
    q = rows[:, o + 4:o + 8]
    q[:] = quats
    zero = ~q.any(axis=1)
    if zero.any():
        q[zero] = (1.0, 0.0, 0.0, 0.0)
    if lidar is not None:
        rows[:, ROW_FLOATS:] = lidar
    return rows


class PlyStreamWriter:
    """Writes PLY rows in chunks to ``path`` (atomically: a temporary file beside it, renamed
    by :meth:`close`; removed by :meth:`abort` or when the ``with`` block raises).

    Example::

        with PlyStreamWriter(Path("scene.ply")) as out:
            for chunk in chunks:          # (n, 62) float32 rows from pack_rows
                out.write(chunk)

    ``lidar``: the rows carry :data:`LIDAR_PROPERTIES` too ((n, 64)).
    """

    def __init__(self, path: Path, comments: tuple[str, ...] = (), lidar: bool = False) -> None:
        self.path = Path(path)
        self.comments = tuple(c.replace("\n", " ") for c in comments)
        self.lidar = lidar
        self.row_floats = ROW_FLOATS + (len(LIDAR_PROPERTIES) if lidar else 0)
        self.count = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self._tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".tmp")
        self._file = os.fdopen(fd, "wb")
        self._header_len = len(ply_header(10 ** (_COUNT_WIDTH - 1), self.comments, lidar=lidar))
        self._file.write(ply_header(10 ** (_COUNT_WIDTH - 1), self.comments, lidar=lidar))

    def write(self, rows: np.ndarray) -> None:
        """Append (n, 62) rows ((n, 64) with LiDAR features; cast to little-endian float32)."""
        if rows.ndim != 2 or rows.shape[1] != self.row_floats:
            raise ValueError(f"PLY rows must be (n, {self.row_floats}), got {rows.shape}")
        self._file.write(np.ascontiguousarray(rows, dtype=ROW_DTYPE).tobytes())
        self.count += len(rows)

    def close(self) -> Path:
        """Patch the vertex count into the header, flush, fsync and rename into place."""
        header = ply_header(self.count, self.comments, lidar=self.lidar)
        header = ply_header(self.count, self.comments, pad=self._header_len - len(header), lidar=self.lidar)
        assert len(header) == self._header_len
        self._file.seek(0)
        self._file.write(header)
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        umask = os.umask(0o022)  # read by setting; restored at once
        os.umask(umask)
        os.chmod(self._tmp, 0o666 & ~umask)
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        if not self._file.closed:
            self._file.close()
        if os.path.exists(self._tmp):
            os.unlink(self._tmp)

    def __enter__(self) -> "PlyStreamWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> Optional[bool]:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return None
