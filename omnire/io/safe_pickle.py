"""Restricted unpickling: pickles are code, so only an allowlist of data classes may load.

Each reader passes the allowlist its format needs (:class:`PickleAllowlist`): numpy arrays
and plain containers (:data:`NUMPY_DATA`) for every reader, plus e.g. pandas' DataFrame
reconstructors for PandaSet's ``*.pkl.gz`` or stand-ins for chumpy arrays in SMPL model
files. Anything outside the allowlist (``os.system``, ``builtins.eval``, arbitrary classes)
raises :class:`UnsafePickleError` naming the file and the refused global.

Reads are bounded: a file larger than ``max_bytes``, or a gzip stream that would expand
beyond it, is refused before it is expanded in memory (a 1.6 MB gzip can hold gigabytes).
"""
from __future__ import annotations

import dataclasses
import io
import pickle
import zlib
from pathlib import Path
from typing import Any, Mapping


from omnire.errors import MissingFileError, UserError


class PickleReadError(UserError, pickle.UnpicklingError):
    """A pickle file is damaged, too large, or not a pickle (the message names it)."""


class UnsafePickleError(PickleReadError):
    """A pickle asked for a global that is not on the allowlist: refused as unsafe."""


class StandIn:
    """Base of objects that replace a refused class during unpickling; :func:`plain` swaps
    each for the value of its :meth:`to_plain`."""

    def to_plain(self) -> Any:
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class PickleAllowlist:
    """What a pickle may refer to: globals resolved by import (data classes and their
    reconstructors only, never a function that reads files or evaluates code), and stand-in
    classes used in place of others (module, name) -> class."""

    globals: frozenset[tuple[str, str]]
    standins: Mapping[tuple[str, str], type] = dataclasses.field(default_factory=dict)

    def __or__(self, other: "PickleAllowlist") -> "PickleAllowlist":
        return PickleAllowlist(self.globals | other.globals, {**self.standins, **other.standins})


NUMPY_DATA = PickleAllowlist(frozenset({
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
}))
"""numpy arrays, scalars and plain containers: what every reader accepts."""

DEFAULT_MAX_BYTES = 256 * 2**20


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that resolves only the globals of ``allow`` (stand-ins first)."""

    def __init__(self, file: Any, source: str, allow: PickleAllowlist = NUMPY_DATA) -> None:
        super().__init__(file, encoding="latin1")
        self.source = source
        self.allow = allow

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self.allow.standins:
            return self.allow.standins[(module, name)]
        if (module, name) in self.allow.globals:
            return super().find_class(module, name)
        raise UnsafePickleError(
            f"{self.source}: refused as unsafe: it refers to {module}.{name}, which is not a data type "
            "this reader accepts; the file may be corrupt or malicious"
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


def read_capped(path: Path, max_bytes: int) -> bytes:
    """The bytes of ``path``, gunzipped when it is gzip-compressed, refusing (before
    expanding it) a file whose content would exceed ``max_bytes``."""
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{path}: no such file")
    if path.stat().st_size > max_bytes:
        raise PickleReadError(f"{path}: {path.stat().st_size} bytes, more than this reader accepts ({max_bytes})")
    raw = path.read_bytes()
    if raw[:2] != b"\x1f\x8b":
        return raw
    inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
    out, total = [], 0
    data = raw
    try:
        while data:
            chunk = inflater.decompress(data, 1 << 20)  # at most 1 MB per call
            total += len(chunk)
            if total > max_bytes:
                raise PickleReadError(f"{path}: expands to more than {max_bytes} bytes; refused (this format "
                                      "holds far less: the file is corrupt or a decompression bomb)")
            out.append(chunk)
            data = inflater.unconsumed_tail
            if inflater.eof:
                break
    except zlib.error as exc:
        raise PickleReadError(f"{path}: damaged gzip data ({exc})") from None
    if not inflater.eof:
        raise PickleReadError(f"{path}: truncated gzip data")
    return b"".join(out)


def load(path: str | Path, allow: PickleAllowlist = NUMPY_DATA, max_bytes: int = DEFAULT_MAX_BYTES) -> Any:
    """Load a (possibly gzip-compressed) pickle through the allowlist ``allow``, reading at
    most ``max_bytes`` (after decompression).

    Raises:
        MissingFileError: the file does not exist (message names it).
        UnsafePickleError: the pickle refers to a global outside the allowlist.
        PickleReadError: the file is too large, damaged, or not a pickle.
    """
    path = Path(path)
    raw = read_capped(path, max_bytes)
    try:
        return plain(RestrictedUnpickler(io.BytesIO(raw), str(path), allow).load())
    except PickleReadError:
        raise
    except Exception as exc:
        raise PickleReadError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from exc

