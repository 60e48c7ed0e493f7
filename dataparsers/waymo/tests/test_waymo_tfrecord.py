"""TFRecord framing: round trip, checksums, damage and truncation reported with the byte offset."""
from __future__ import annotations

import os
import struct

import pytest

from omnire.api import SceneDataError
from omnire_waymo.tfrecord import TFRecordError, TFRecordReader, TFRecordWriter, masked_crc32c

RECORDS = [b"", b"a", os.urandom(1000), b"\x00" * 70000, b"last record"]


def write(path, records=RECORDS):
    with TFRecordWriter(path) as w:
        for r in records:
            w.write(r)
    return path


def test_crc32c_and_mask_known_values():
    import google_crc32c

    assert google_crc32c.value(b"123456789") == 0xE3069283  # the CRC-32C check value
    # masked = rotate right by 15 bits, plus 0xa282ead8
    crc = 0xE3069283
    assert masked_crc32c(b"123456789") == ((((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF)


def test_round_trip_sequential_and_indexed(tmp_path):
    path = write(tmp_path / "x.tfrecord")
    assert path.stat().st_size == sum(len(r) + 16 for r in RECORDS)
    assert not list(tmp_path.glob(".*.tmp"))  # temp file renamed away
    with TFRecordReader(path) as rd:
        assert list(rd) == RECORDS
        spans = rd.index()
        assert [s.length for s in spans] == [len(r) for r in RECORDS]
        assert spans[0].offset == 0 and spans[1].offset == 16
        assert rd.read(spans[3]) == RECORDS[3] and rd.read(spans[0]) == b""  # random access


def test_writer_failure_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with TFRecordWriter(tmp_path / "x.tfrecord") as w:
            w.write(b"abc")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_payload_damage_detected_with_offset(tmp_path):
    path = write(tmp_path / "x.tfrecord")
    data = bytearray(path.read_bytes())
    offset = 16 + 17  # third record starts after the empty one (16 B) and b"a" (17 B)
    data[offset + 12 + 500] ^= 0x01  # one bit inside its payload
    path.write_bytes(bytes(data))
    with TFRecordReader(path) as rd:
        spans = rd.index()  # headers are intact: indexing works
        assert rd.read(spans[1]) == b"a"
        with pytest.raises(TFRecordError, match=rf"x\.tfrecord: damaged record at byte offset {offset} .*CRC-32C"):
            rd.read(spans[2])
        with pytest.raises(SceneDataError):  # a user error of the reader family
            list(rd)
    with TFRecordReader(path, check_crc=False) as rd:  # opt-out reads the damaged bytes
        assert len(rd.read(rd.index()[2])) == 1000


def test_footer_damage_detected(tmp_path):
    path = write(tmp_path / "x.tfrecord", [b"payload"])
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    with TFRecordReader(path) as rd, pytest.raises(TFRecordError, match="byte offset 0"):
        rd.read(rd.index()[0])


def test_header_damage_detected(tmp_path):
    path = write(tmp_path / "x.tfrecord")
    data = bytearray(path.read_bytes())
    data[16] ^= 0x40  # length field of the second record
    path.write_bytes(bytes(data))
    with TFRecordReader(path) as rd, pytest.raises(TFRecordError, match=r"damaged record header at byte offset 16\b"):
        rd.index()


@pytest.mark.parametrize("cut", [5, 12 + 3, 40])
def test_truncation_detected(tmp_path, cut):
    path = write(tmp_path / "x.tfrecord", [b"x" * 30, b"y" * 30])
    data = path.read_bytes()
    path.write_bytes(data[: 46 + cut])  # second record (offset 46) cut short
    with TFRecordReader(path) as rd, pytest.raises(TFRecordError, match=r"truncated record.* at byte offset 46"):
        rd.index()


def test_not_a_tfrecord(tmp_path):
    path = tmp_path / "x.tfrecord"
    path.write_bytes(b"JFIF this is some other file" * 3)
    with TFRecordReader(path) as rd, pytest.raises(TFRecordError, match="not a TFRecord"):
        rd.index()


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.tfrecord"):
        TFRecordReader(tmp_path / "nope.tfrecord")


def test_reads_a_file_written_by_tensorflow(real_frame):
    # The shared frame was written by TensorFlow: its checksums validate our masking.
    with TFRecordReader(real_frame) as rd:
        spans = rd.index()
        assert len(spans) == 1 and spans[0].end == real_frame.stat().st_size
        payload = rd.read(spans[0])
    assert len(payload) == struct.unpack("<Q", real_frame.read_bytes()[:8])[0]
