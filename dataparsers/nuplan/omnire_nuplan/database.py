"""A nuPlan log database, read with the standard library's :mod:`sqlite3` (no devkit).

A nuPlan log is one SQLite file (``<log>.db``; schema: nuplan-devkit ``docs/nuplan_schema.md``,
column types in ``nuplan/database/nuplan_db_orm/*.py`` and the ``CREATE TABLE`` statements of
``nuplan/database/nuplan_db/test/minimal_db_test_utils.py``):

- every ``token`` and foreign key is an 8-byte BLOB (``sql_types.HexLen8``; the devkit shows
  it as 16 hex digits, ``bytes.hex()``);
- ``camera.translation / rotation / intrinsic / distortion`` and ``lidar.translation /
  rotation`` are pickled Python lists (``sql_types.SimplePickleType``; the devkit pickles its
  ``data_types.Translation`` / ``Rotation`` / ``CameraIntrinsic``, which are ``list``
  subclasses). Pickles are code, so they are decoded by :class:`ListUnpickler`, which builds
  lists of numbers and refuses any other global;
- the other numbers are plain INTEGER / FLOAT columns.

SQLite columns are dynamically typed, so every value is checked for its type where it is
used: a wrong one is a one-line :class:`NuPlanDataError` naming the database file, the table,
the row's token and the column.
"""
from __future__ import annotations

import contextlib
import copyreg
import io
import math
import pickle
import sqlite3
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from omnire.api import SceneDataError, quat_to_se3


class NuPlanDataError(SceneDataError):
    """A nuPlan database or blob is malformed or inconsistent (the message names file, table and column)."""


class NuPlanFileMissing(NuPlanDataError, FileNotFoundError):
    """A nuPlan database or sensor blob is missing (the message names the path)."""


TABLE_COLUMNS: dict[str, tuple[str, ...]] = {
    "log": ("token", "logfile", "location"),
    "ego_pose": ("token", "timestamp", "x", "y", "z", "qw", "qx", "qy", "qz"),
    "camera": ("token", "channel", "translation", "rotation", "intrinsic", "distortion", "width", "height"),
    "image": ("token", "ego_pose_token", "camera_token", "filename_jpg", "timestamp"),
    "lidar": ("token", "channel", "translation", "rotation"),
    "lidar_pc": ("token", "ego_pose_token", "lidar_token", "filename", "timestamp"),
    "lidar_box": ("token", "lidar_pc_token", "track_token", "x", "y", "z", "width", "length", "height", "yaw"),
    "track": ("token", "category_token"),
    "category": ("token", "name"),
}
"""Columns this reader uses per table (a subset of the nuPlan schema)."""

MAX_PICKLE_BYTES = 1 << 16
"""A pickled calibration list is a few hundred bytes; larger cells are refused unread."""
_SQL_PARAMS = 900
"""Tokens per ``IN (...)`` query (SQLite's default limit of bound parameters is 999)."""


class ListUnpickler(pickle.Unpickler):
    """Unpickles the devkit's pickled calibration lists: ``list`` and its ``data_types``
    subclasses become plain lists; any other global is refused (a pickle naming e.g.
    ``os.system`` would run it)."""

    LISTS = frozenset({("builtins", "list")} | {("nuplan.database.common.data_types", name)
                                               for name in ("Translation", "Rotation", "CameraIntrinsic")})

    def find_class(self, module: str, name: str) -> Any:
        module = {"copy_reg": "copyreg", "__builtin__": "builtins"}.get(module, module)  # protocol 0/1 names
        if (module, name) in self.LISTS:
            return list
        if (module, name) == ("copyreg", "_reconstructor"):  # protocol 0/1 pickles of list subclasses
            return copyreg._reconstructor
        raise pickle.UnpicklingError(f"refers to {module}.{name}, which is not a list type; refused as unsafe")


def _short(value: Any) -> str:
    """A cell for a message: at most 80 characters (a cell can be a large BLOB)."""
    text = repr(value[:81] if isinstance(value, (str, bytes)) else value)
    return text if len(text) <= 80 else text[:77] + "..."


def token_hex(value: Any) -> str:
    """A token cell as the devkit prints it: 8-byte BLOB -> 16 hex digits (text kept as is)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    return str(value)


class Row:
    """One row of a table, with typed, checked access to its columns."""

    def __init__(self, db: "LogDatabase", table: str, values: sqlite3.Row) -> None:
        self.db, self.table, self.values = db, table, values

    @property
    def token(self) -> str:
        return self.ref("token")

    def error(self, column: str, expected: str) -> NuPlanDataError:
        return NuPlanDataError(f"{self.db.path}: table {self.table} row {token_hex(self.values['token'])}: "
                               f"column {column} = {_short(self.values[column])}; expected {expected}")

    def ref(self, column: str) -> str:
        """A token / foreign key (BLOB or text) as hex text."""
        v = self.values[column]
        if not isinstance(v, (bytes, str)) or not v:
            raise self.error(column, "a token (8-byte BLOB)")
        return token_hex(v)

    def integer(self, column: str) -> int:
        v = self.values[column]
        if not isinstance(v, int):
            raise self.error(column, "an INTEGER (microseconds for timestamps)")
        return v

    def number(self, column: str) -> float:
        v = self.values[column]
        if not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.error(column, "a finite number")
        return float(v)

    def text(self, column: str) -> str:
        v = self.values[column]
        if not isinstance(v, str) or not v:
            raise self.error(column, "non-empty text")
        return v

    def pickled(self, column: str, shape: tuple[int, ...]) -> np.ndarray:
        """A pickled list of numbers as a finite float64 array of ``shape``."""
        v = self.values[column]
        want = f"a pickled list of {'x'.join(map(str, shape))} finite numbers"
        if not isinstance(v, bytes) or len(v) > MAX_PICKLE_BYTES:
            raise self.error(column, want)
        try:
            obj = ListUnpickler(io.BytesIO(v)).load()
        except (pickle.UnpicklingError, EOFError, TypeError, ValueError, AttributeError, IndexError,
                KeyError, OverflowError, MemoryError, ImportError, RecursionError) as exc:
            raise NuPlanDataError(f"{self.db.path}: table {self.table} row {token_hex(self.values['token'])}: "
                                  f"column {column} is not {want} ({exc})") from None
        # The nesting is checked before numpy sees it: shared references could make a small
        # pickle a huge nested list.
        if not _nested_numbers(obj, shape):
            got = f"a {type(obj).__name__}" + (f" of {len(obj)} items" if isinstance(obj, (list, tuple)) else "")
            raise NuPlanDataError(f"{self.db.path}: table {self.table} row {token_hex(self.values['token'])}: "
                                  f"column {column} unpickles to {got}; expected {want}")
        a = np.asarray(obj, dtype=np.float64)
        if not np.isfinite(a).all():
            raise NuPlanDataError(f"{self.db.path}: table {self.table} row {token_hex(self.values['token'])}: "
                                  f"column {column} unpickles to {a.tolist()}; expected {want}")
        return a


def _nested_numbers(obj: Any, shape: tuple[int, ...]) -> bool:
    """Whether ``obj`` is nested lists of exactly ``shape`` holding int/float numbers."""
    if not shape:
        return isinstance(obj, (int, float)) and not isinstance(obj, bool)
    return (isinstance(obj, (list, tuple)) and len(obj) == shape[0]
            and all(_nested_numbers(o, shape[1:]) for o in obj))


class LogDatabase(contextlib.AbstractContextManager):
    """A nuPlan log database opened read-only (the file is never written)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise NuPlanFileMissing(f"{self.path}: no such nuPlan log database (expected <log>.db, e.g. "
                                    "nuplan-v1.1/splits/mini/<log>.db)")
        # immutable: no lock or journal files appear beside the database.
        self.conn = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)
        self.conn.row_factory = sqlite3.Row
        try:
            names = [r[0] for r in self.conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
            self.columns = {n: {r[1] for r in self.conn.execute(f'PRAGMA table_info("{n}")')} for n in names}
        except sqlite3.DatabaseError as exc:
            self.conn.close()
            raise NuPlanDataError(f"{self.path}: not a readable SQLite database ({exc})") from None

    def close(self) -> None:
        self.conn.close()

    def __exit__(self, *exc) -> None:
        self.close()

    def has_table(self, table: str) -> bool:
        return table in self.columns

    def _check_table(self, table: str) -> None:
        need = TABLE_COLUMNS[table]
        if table not in self.columns:
            raise NuPlanDataError(f"{self.path}: no table {table} (a nuPlan log database holds "
                                  f"{', '.join(sorted(TABLE_COLUMNS))}); is this a nuPlan log?")
        missing = [c for c in need if c not in self.columns[table]]
        if missing:
            raise NuPlanDataError(f"{self.path}: table {table} lacks column(s) {', '.join(missing)}; "
                                  f"this reader needs {', '.join(need)}")

    def rows(self, table: str, where: str = "", args: Sequence[Any] = (), order: str = "") -> list[Row]:
        """Rows of ``table`` (all columns), optionally filtered (``where`` with ``?`` for
        ``args``) and ordered (``order``: an ORDER BY clause's column list)."""
        self._check_table(table)
        sql = f'SELECT * FROM "{table}"' + (f" WHERE {where}" if where else "") + (f" ORDER BY {order}" if order else "")
        try:
            return [Row(self, table, r) for r in self.conn.execute(sql, tuple(args))]
        except sqlite3.DatabaseError as exc:
            raise NuPlanDataError(f"{self.path}: table {table} cannot be read ({exc})") from None

    def rows_with(self, table: str, column: str, values: Iterable[Any]) -> list[Row]:
        """Rows of ``table`` whose ``column`` is one of ``values`` (raw cell values, e.g.
        token BLOBs), queried in batches."""
        values = list(dict.fromkeys(values))
        out: list[Row] = []
        for i in range(0, len(values), _SQL_PARAMS):
            chunk = values[i:i + _SQL_PARAMS]
            out.extend(self.rows(table, f'"{column}" IN ({",".join("?" * len(chunk))})', chunk))
        return out


def index(rows: Iterable[Row]) -> dict[str, Row]:
    """Rows by their token (hex)."""
    return {r.token: r for r in rows}


def lookup(table_rows: dict[str, Row], row: Row, column: str, table: str) -> Row:
    """The row of ``table`` that ``row.column`` points at, or an error naming the dangling key."""
    key = row.ref(column)
    hit = table_rows.get(key)
    if hit is None:
        raise NuPlanDataError(f"{row.db.path}: table {row.table} row {row.token}: column {column} = {key} "
                              f"names no row of table {table}")
    return hit


def pose(translation: np.ndarray, quaternion_wxyz: np.ndarray, row: Row, column: str) -> np.ndarray:
    """(4, 4) from a translation (3,) and a unit quaternion (w, x, y, z) (4,) of ``row``
    (``column`` names the quaternion's column(s) in the error)."""
    if abs(np.linalg.norm(quaternion_wxyz) - 1.0) > 1e-3:
        raise NuPlanDataError(f"{row.db.path}: table {row.table} row {row.token}: column {column} = "
                              f"{quaternion_wxyz.tolist()} is not a unit quaternion (w, x, y, z)")
    return quat_to_se3(quaternion_wxyz, translation)


def raw_tokens(rows: Iterable[Row], column: str = "token") -> list[Any]:
    """The raw cells (BLOBs) of ``column``, to query other tables by them."""
    return [r.values[column] for r in rows]
