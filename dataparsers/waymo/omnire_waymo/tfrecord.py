"""TFRecord framing without TensorFlow: read a file record by record, write one atomically.

A TFRecord file is a sequence of records, each::

    uint64 length          little-endian payload size in bytes
    uint32 masked_crc32c(length bytes)
    byte   payload[length]
    uint32 masked_crc32c(payload)

with ``masked(c) = ((c >> 15) | (c << 17)) + 0xa282ead8`` (mod 2^32) over the CRC-32C
(Castagnoli) checksum. Reading never holds more than one payload in memory: :meth:`index`
walks the headers only (seeking over the payloads), :meth:`read` fetches one payload and
checks its checksum. A damaged or truncated record raises :class:`TFRecordError` naming the
file and the byte offset of the record.
"""
from __future__ import annotations

import os
import struct
import tempfile
from pathlib import Path
from typing import BinaryIO, Iterator, NamedTuple, Optional

import google_crc32c

from omnire.api import SceneDataError
from omnire.api import MissingFileError

_MASK_DELTA = 0xA282EAD8
_HEADER = struct.Struct("<QI")  # length, masked crc of the length bytes
_FOOTER = struct.Struct("<I")  # masked crc of the payload


class TFRecordError(SceneDataError):
    """A TFRecord file is truncated or a record fails its checksum (message: file and byte offset)."""


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC-32C of ``data`` (uint32)."""
    crc = google_crc32c.value(bytes(data))
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


class RecordSpan(NamedTuple):
    """Where one record lies in the file: ``offset`` of its 12-byte header, payload ``length``."""

    offset: int
    length: int

    @property
    def payload_offset(self) -> int:
        return self.offset + _HEADER.size

    @property
    def end(self) -> int:
        return self.offset + _HEADER.size + self.length + _FOOTER.size


class TFRecordReader:
    """Random and sequential access to the records of one TFRecord file.

    Use as a context manager (or call :meth:`close`). ``check_crc=False`` skips the payload
    checksum (the header checksum is always checked: a wrong length would misframe the rest).
    """

    def __init__(self, path: str | Path, check_crc: bool = True) -> None:
        self.path = Path(path)
        self.check_crc = check_crc
        try:
            self._f: BinaryIO = open(self.path, "rb")
        except FileNotFoundError:
            raise MissingFileError(f"{self.path}: TFRecord file not found") from None
        self.size = os.fstat(self._f.fileno()).st_size

    def __enter__(self) -> "TFRecordReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    def _header(self, offset: int) -> RecordSpan:
        self._f.seek(offset)
        head = self._f.read(_HEADER.size)
        if len(head) < _HEADER.size:
            raise TFRecordError(
                f"{self.path}: truncated record header at byte offset {offset} ({len(head)} of "
                f"{_HEADER.size} bytes; file size {self.size})"
            )
        length, crc = _HEADER.unpack(head)
        if crc != masked_crc32c(head[:8]):
            raise TFRecordError(
                f"{self.path}: damaged record header at byte offset {offset} (length field fails its "
                "CRC-32C check); the file is corrupt or not a TFRecord file"
            )
        span = RecordSpan(offset, length)
        if span.end > self.size:
            raise TFRecordError(
                f"{self.path}: truncated record at byte offset {offset}: its header announces {length} "
                f"payload bytes, but the file ends at byte {self.size} (needs {span.end})"
            )
        return span

    def index(self) -> list[RecordSpan]:
        """Spans of all records, from the headers alone (payloads are skipped, not read)."""
        spans, offset = [], 0
        while offset < self.size:
            span = self._header(offset)
            spans.append(span)
            offset = span.end
        return spans

    def read(self, span: RecordSpan) -> bytes:
        """The payload of the record at ``span`` (from :meth:`index`), checksum verified."""
        self._f.seek(span.payload_offset)
        payload = self._f.read(span.length)
        footer = self._f.read(_FOOTER.size)
        if len(payload) != span.length or len(footer) != _FOOTER.size:
            raise TFRecordError(f"{self.path}: truncated record at byte offset {span.offset}")
        if self.check_crc and _FOOTER.unpack(footer)[0] != masked_crc32c(payload):
            raise TFRecordError(
                f"{self.path}: damaged record at byte offset {span.offset} ({span.length}-byte payload "
                "fails its CRC-32C check)"
            )
        return payload

    def __iter__(self) -> Iterator[bytes]:
        """Payloads in file order, one at a time."""
        offset = 0
        while offset < self.size:
            span = self._header(offset)
            yield self.read(span)
            offset = span.end


class TFRecordWriter:
    """Writes records to a temporary file beside ``path``; :meth:`close` renames it into place
    (so readers never see a half-written file). Use as a context manager; on an exception
    the temporary file is removed and ``path`` is left untouched."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        self._tmp = Path(tmp)
        self._f: Optional[BinaryIO] = os.fdopen(fd, "wb")
        self.bytes_written = 0

    def write(self, payload: bytes) -> None:
        length = struct.pack("<Q", len(payload))
        self._f.write(length + struct.pack("<I", masked_crc32c(length)))
        self._f.write(payload)
        self._f.write(_FOOTER.pack(masked_crc32c(payload)))
        self.bytes_written += _HEADER.size + len(payload) + _FOOTER.size

    def close(self) -> None:
        if self._f is None:
            return
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()
        self._f = None
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> "TFRecordWriter":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
