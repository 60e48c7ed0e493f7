"""Restricted unpickling: pickles are code, so only an allowlist of data classes may load.

Used for PandaSet's pandas DataFrames (``*.pkl.gz``), the reference implementation's
``humanpose/smpl.pkl`` and user-given SMPL model files. Anything outside the allowlist
(``os.system``, ``builtins.eval``, arbitrary classes) raises :class:`UnsafePickleError`
naming the file and the refused global.

SMPL model pickles made with chumpy hold ``chumpy.ch.Ch`` objects and scipy sparse
matrices; both are mapped to small stand-ins that yield plain numpy arrays, so neither
chumpy nor scipy needs to be installed.
"""
from __future__ import annotations

import gzip
import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np
from omnire.errors import MissingFileError, UserError


class PickleReadError(UserError, pickle.UnpicklingError):
    """A pickle file is damaged or not a pickle (the message names it)."""


class UnsafePickleError(PickleReadError):
    """A pickle asked for a global that is not on the allowlist: refused as unsafe."""


class StandIn:
    """Base of objects that replace a refused class during unpickling; :func:`plain` swaps
    each for the value of its :meth:`to_plain`. Readers with their own stand-ins (e.g.
    joblib arrays) subclass it."""

    def to_plain(self) -> Any:
        raise NotImplementedError


class _ChumpyArray(StandIn):
    """Stand-in for ``chumpy.ch.Ch``: keeps the ``x`` array from its pickled state."""

    def to_plain(self) -> Any:
        return self.x

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.x: np.ndarray | None = None

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, dict):
            self.x = np.asarray(state.get("x", state.get("_x")))
        else:
            self.x = np.asarray(state)


class _SparseMatrix(StandIn):
    """Stand-in for scipy ``csc_matrix`` / ``csr_matrix``; :meth:`toarray` densifies."""

    def to_plain(self) -> Any:
        return self.dense()  # type: ignore[attr-defined]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: dict = {}

    def __setstate__(self, state: Any) -> None:
        self.state = dict(state)

    def toarray(self, csc: bool) -> np.ndarray:
        s = self.state
        shape = tuple(s["_shape"]) if "_shape" in s else tuple(s["shape"])
        data, indices, indptr = (np.asarray(s[k]) for k in ("data", "indices", "indptr"))
        out = np.zeros(shape, dtype=data.dtype)
        major = shape[1] if csc else shape[0]
        for j in range(major):
            rows = indices[indptr[j] : indptr[j + 1]]
            vals = data[indptr[j] : indptr[j + 1]]
            if csc:
                out[rows, j] = vals
            else:
                out[j, rows] = vals
        return out


class _CscMatrix(_SparseMatrix):
    def dense(self) -> np.ndarray:
        return self.toarray(csc=True)


class _CsrMatrix(_SparseMatrix):
    def dense(self) -> np.ndarray:
        return self.toarray(csc=False)




# Globals resolved through the normal import machinery once allowed (data classes and their
# reconstructors only; no function that reads files or evaluates expressions).
_ALLOWED_IMPORTS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("builtins", "slice"),
    ("builtins", "set"),
    ("builtins", "frozenset"),
    ("builtins", "complex"),
    ("collections", "OrderedDict"),
    ("_codecs", "encode"),  # protocol-2 pickles store bytes as codecs.encode(str, "latin1")
    ("pandas", "DataFrame"),
    ("pandas", "Index"),
    ("pandas", "RangeIndex"),
    ("pandas", "Series"),
    ("pandas._libs.internals", "_unpickle_block"),
    ("pandas.core.frame", "DataFrame"),
    ("pandas.core.series", "Series"),
    ("pandas.core.indexes.base", "Index"),
    ("pandas.core.indexes.base", "_new_Index"),
    ("pandas.core.indexes.range", "RangeIndex"),
    ("pandas.core.internals.managers", "BlockManager"),
    ("pandas.core.internals.managers", "SingleBlockManager"),
    ("pandas.core.internals.blocks", "new_block"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch", "FloatStorage"),
    ("torch", "LongStorage"),
    ("torch", "BoolStorage"),
    ("torch", "DoubleStorage"),
}

_STANDINS = {
    ("chumpy.ch", "Ch"): _ChumpyArray,
    ("chumpy.reordering", "Select"): _ChumpyArray,
    ("scipy.sparse.csc", "csc_matrix"): _CscMatrix,
    ("scipy.sparse._csc", "csc_matrix"): _CscMatrix,
    ("scipy.sparse.csr", "csr_matrix"): _CsrMatrix,
    ("scipy.sparse._csr", "csr_matrix"): _CsrMatrix,
}


class RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file: Any, source: str) -> None:
        super().__init__(file, encoding="latin1")
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _STANDINS:
            return _STANDINS[(module, name)]
        if (module, name) in _ALLOWED_IMPORTS:
            return super().find_class(module, name)
        raise UnsafePickleError(
            f"{self.source}: refusing to load global {module}.{name} (not a known data type); "
            "the file may be corrupt or malicious"
        )


def plain(obj: Any) -> Any:
    """Replace stand-ins (chumpy arrays, sparse matrices, ...) by their values, recursively."""
    if isinstance(obj, StandIn):
        return obj.to_plain()
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [plain(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(plain(v) for v in obj)
    return obj


def load(path: str | Path) -> Any:
    """Load a (possibly gzip-compressed) pickle through the allowlist.

    Raises:
        FileNotFoundError: the file does not exist (message names it).
        UnsafePickleError: the pickle refers to a global outside the allowlist.
        pickle.UnpicklingError: the file is not a valid pickle (message names it).
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{path}: no such file")
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    try:
        return plain(RestrictedUnpickler(io.BytesIO(raw), str(path)).load())
    except UnsafePickleError:
        raise
    except Exception as exc:
        raise PickleReadError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from exc
