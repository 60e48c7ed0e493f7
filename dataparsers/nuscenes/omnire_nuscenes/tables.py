"""nuScenes JSON tables, read with the standard library and streamed.

A nuScenes release keeps its database as one JSON file per table (``v1.0-mini/scene.json``,
``sample_data.json``, ...; schema: nuscenes-devkit ``docs/schema_nuscenes.md``), each a
top-level array of records linked by 32-hex-digit tokens. The trainval tables are large
(millions of ``sample_data`` and ``ego_pose`` records), so they are never loaded whole:
:func:`iter_json_array` decodes one record at a time from a bounded buffer and
:func:`load_table` keeps only the records a filter selects (those of one scene).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Iterator, Optional

import numpy as np

from omnire.api import SceneDataError, quat_to_se3


class NuScenesDataError(SceneDataError):
    """A nuScenes table or file is malformed or inconsistent (the message names file and field)."""


class NuScenesFileMissing(NuScenesDataError, FileNotFoundError):
    """A nuScenes table or data file is missing (the message names the path)."""


TABLE_FIELDS: dict[str, tuple[str, ...]] = {
    "scene": ("token", "name", "log_token", "nbr_samples", "first_sample_token", "last_sample_token"),
    "log": ("token", "logfile", "location"),
    "sample": ("token", "timestamp", "scene_token", "prev", "next"),
    "sample_data": ("token", "sample_token", "ego_pose_token", "calibrated_sensor_token", "filename",
                    "fileformat", "width", "height", "timestamp", "is_key_frame", "prev", "next"),
    "ego_pose": ("token", "translation", "rotation", "timestamp"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation", "camera_intrinsic"),
    "sensor": ("token", "channel", "modality"),
    "sample_annotation": ("token", "sample_token", "instance_token", "translation", "size", "rotation"),
    "instance": ("token", "category_token"),
    "category": ("token", "name"),
}
"""Fields this reader uses per table (a subset of the nuScenes schema); a record lacking one
is an error naming the table file, the record's token and the field."""

_WS = " \t\r\n"


def iter_json_array(path: Path, chunk_chars: int = 1 << 20) -> Iterator[Any]:
    """Yield the elements of a JSON file whose top level is one array, decoding them one at
    a time from a buffer of about ``chunk_chars`` characters (memory does not grow with the
    file). Raises :class:`NuScenesDataError` naming the file and character offset when the
    file is not such an array."""
    decoder = json.JSONDecoder()
    with open(path, "r", encoding="utf-8") as f:
        buf, pos, dropped, eof = "", 0, 0, False

        def more() -> bool:
            nonlocal buf, pos, dropped, eof
            if eof:
                return False
            chunk = f.read(chunk_chars)
            if not chunk:
                eof = True
                return False
            dropped += pos
            buf, pos = buf[pos:] + chunk, 0
            return True

        def skip_ws() -> bool:
            """Advance past whitespace; False at the end of the file."""
            nonlocal pos
            while True:
                while pos < len(buf) and buf[pos] in _WS:
                    pos += 1
                if pos < len(buf):
                    return True
                if not more():
                    return False

        def fail(what: str) -> NuScenesDataError:
            return NuScenesDataError(f"{path}: not a JSON array of records ({what} at character {dropped + pos})")

        if not skip_ws() or buf[pos] != "[":
            raise fail("expected '['")
        pos += 1
        first = True
        while True:
            if not skip_ws():
                raise fail("file ends inside the array")
            if buf[pos] == "]":
                pos += 1
                if skip_ws():
                    raise fail("data after the closing ']'")
                return
            if not first:
                if buf[pos] != ",":
                    raise fail("expected ',' or ']'")
                pos += 1
                if not skip_ws():
                    raise fail("file ends inside the array")
            while True:
                try:
                    value, end = decoder.raw_decode(buf, pos)
                    break
                except RecursionError:  # a record nested thousands deep: no nuScenes record is
                    raise NuScenesDataError(f"{path}: element nested too deeply near character {dropped + pos} "
                                            "(nuScenes records are objects of numbers, strings and short lists)"
                                            ) from None
                except json.JSONDecodeError as exc:
                    # Most often the element continues in the next chunk.
                    if not more():
                        raise NuScenesDataError(f"{path}: invalid JSON near character {dropped + exc.pos} "
                                                f"({exc.msg})") from None
            pos = end
            first = False
            yield value


def load_table(tables: Path, name: str, keep: Optional[Callable[[dict], bool]] = None) -> list[dict]:
    """Records of table ``name`` (``<tables>/<name>.json``) for which ``keep`` is true (all
    when None), each checked for the fields in :data:`TABLE_FIELDS`."""
    path = tables / f"{name}.json"
    if not path.is_file():
        raise NuScenesFileMissing(
            f"{path}: missing nuScenes table {name!r} (the version folder, e.g. v1.0-mini/, holds one JSON file "
            f"per table: {', '.join(sorted(TABLE_FIELDS))})"
        )
    fields = TABLE_FIELDS.get(name, ("token",))
    out = []
    for i, rec in enumerate(iter_json_array(path)):
        if not isinstance(rec, dict):
            raise NuScenesDataError(f"{path}: element {i} is a {type(rec).__name__}, expected a record (JSON object)")
        if keep is not None:
            try:
                if not keep(rec):
                    continue
            except KeyError as exc:
                raise _missing_field(path, i, rec, exc.args[0]) from None
        for key in fields:
            if key not in rec:
                raise _missing_field(path, i, rec, key)
        if "timestamp" in fields:
            stamp = rec["timestamp"]
            if not isinstance(stamp, int) or isinstance(stamp, bool) or stamp < 0:
                raise NuScenesDataError(f"{path}: record {i} (token {rec.get('token', '?')!r}) field 'timestamp' = "
                                        f"{stamp!r}; expected an integer number of microseconds >= 0")
        out.append(rec)
    return out


def _missing_field(path: Path, i: int, rec: dict, key: str) -> NuScenesDataError:
    token = rec.get("token", "?")
    return NuScenesDataError(f"{path}: record {i} (token {token!r}) lacks field {key!r}; "
                             f"{path.stem} records need {', '.join(TABLE_FIELDS.get(path.stem, ('token',)))}")


def lookup(index: dict[str, dict], token: str, table: str, tables: Path, referrer: str) -> dict:
    """``index[token]`` or an error saying which record's field points nowhere."""
    rec = index.get(token)
    if rec is None:
        raise NuScenesDataError(f"{tables / (table + '.json')}: no record with token {token!r} "
                                f"(referenced by {referrer})")
    return rec


def number_array(rec: dict, field: str, shape: tuple[int, ...], table: str, tables: Path) -> np.ndarray:
    """Field ``field`` of a record as a finite float64 array of ``shape``."""
    try:
        a = np.asarray(rec[field], dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.isfinite(a).all():
        raise NuScenesDataError(
            f"{tables / (table + '.json')}: record {rec.get('token', '?')!r} field {field!r} = {rec.get(field)!r}; "
            f"expected {'x'.join(map(str, shape))} finite numbers"
        )
    return a


def pose_matrix(rec: dict, table: str, tables: Path) -> np.ndarray:
    """(4, 4) from a record's ``translation`` (x, y, z metres) and ``rotation`` (w, x, y, z)."""
    t = number_array(rec, "translation", (3,), table, tables)
    q = number_array(rec, "rotation", (4,), table, tables)
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise NuScenesDataError(f"{tables / (table + '.json')}: record {rec['token']!r} field 'rotation' = "
                                f"{rec['rotation']!r} is not a unit quaternion (w, x, y, z)")
    return quat_to_se3(q, t)
