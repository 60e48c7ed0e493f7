"""Loading ``humanpose/smpl.pkl`` safely.

The reference implementation writes it with ``joblib.dump``: numpy arrays become a
``joblib.numpy_pickle.NumpyArrayWrapper`` record followed by the raw array bytes in the
same stream (outside any pickle frame), and torch tensors are pickled through
``torch.storage._load_from_bytes``, whose original runs ``torch.load(weights_only=False)``.

:class:`SmplPickleUnpickler` extends :class:`omnire.io.safe_pickle.RestrictedUnpickler`
(same allowlist, same refusal of everything else) with two stand-ins:

- the array wrapper reads its bytes from the stream itself (numeric dtypes only; object
  arrays, which would be a nested pickle, are refused);
- tensor storages are rebuilt with ``torch.load(..., weights_only=True)``.

joblib itself is not needed. Compressed joblib files (``compress=...``) are refused with a
clear message; gzip-compressed pickles are accepted like in ``safe_pickle.load``.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from omnire.api import safe_pickle


_JOBLIB_WRAPPER = ("joblib.numpy_pickle", "NumpyArrayWrapper")
_TORCH_STORAGE = ("torch.storage", "_load_from_bytes")


class _ArrayFromStream(safe_pickle.StandIn):
    """Stand-in for joblib's ``NumpyArrayWrapper``; ``stream`` is bound per unpickler."""

    stream: io.BytesIO
    source: str

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.array: np.ndarray | None = None

    def to_plain(self) -> Any:
        return self.array

    def __setstate__(self, state: dict) -> None:
        dtype = np.dtype(state["dtype"])
        shape = tuple(int(s) for s in state["shape"])
        if dtype.hasobject:
            raise safe_pickle.UnsafePickleError(
                f"{self.source}: refusing an object array (it would be a nested pickle)")
        if state.get("numpy_array_alignment_bytes") is not None:
            pad = self.stream.read(1)
            if len(pad) != 1:
                raise safe_pickle.PickleReadError(f"{self.source}: truncated array padding")
            self.stream.read(int.from_bytes(pad, "little"))
        count = int(np.prod(shape)) if shape else 1
        raw = self.stream.read(count * dtype.itemsize)
        if len(raw) != count * dtype.itemsize:
            raise safe_pickle.PickleReadError(f"{self.source}: truncated array data ({len(raw)} bytes)")
        arr = np.frombuffer(raw, dtype=dtype).copy()
        if state.get("order", "C") == "F":
            arr = arr.reshape(shape[::-1]).T
        else:
            arr = arr.reshape(shape)
        self.array = arr


def _load_storage(data: bytes) -> Any:
    import torch

    return torch.load(io.BytesIO(data), weights_only=True)


SMPL_SEQUENCES = safe_pickle.NUMPY_DATA | safe_pickle.PickleAllowlist(frozenset({
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch", "FloatStorage"),
    ("torch", "LongStorage"),
    ("torch", "BoolStorage"),
    ("torch", "DoubleStorage"),
}))
"""What ``humanpose/smpl.pkl`` may hold besides joblib records: numpy data and torch tensors."""
SMPL_SEQUENCES_MAX_BYTES = 1 << 30
"""Poses of every pedestrian of a log: ~2 KB per person and frame; 1 GB is far beyond any log."""


class SmplPickleUnpickler(safe_pickle.RestrictedUnpickler):
    """The restricted unpickler plus joblib array records and torch storages (see module doc)."""

    def __init__(self, file: io.BytesIO, source: str) -> None:
        super().__init__(file, source, SMPL_SEQUENCES)
        # A class bound to this stream, so wrappers read their bytes where they stand.
        self._wrapper = type("_BoundArrayFromStream", (_ArrayFromStream,), {"stream": file, "source": source})

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == _JOBLIB_WRAPPER:
            return self._wrapper
        if (module, name) == _TORCH_STORAGE:
            return _load_storage
        return super().find_class(module, name)


def load_smpl_pickle(path: str | Path) -> Any:
    """Load a (joblib or plain) pickle through the restricted unpickler; arrays come back
    as numpy (torch tensors stay tensors; callers convert)."""
    path = Path(path)
    raw = safe_pickle.read_capped(path, SMPL_SEQUENCES_MAX_BYTES)
    if raw[:2] in (b"ZF", b"\x78\x9c", b"\x78\x01", b"\x78\xda") or raw[:3] == b"BZh" or raw[:4] == b"\x28\xb5\x2f\xfd":
        raise safe_pickle.PickleReadError(
            f"{path}: compressed joblib file; re-save it uncompressed (joblib.dump(obj, path, compress=0))"
        )
    stream = io.BytesIO(raw)
    try:
        obj = SmplPickleUnpickler(stream, str(path)).load()
    except safe_pickle.PickleReadError:
        raise
    except Exception as exc:
        raise safe_pickle.PickleReadError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from exc
    return safe_pickle.plain(obj)
