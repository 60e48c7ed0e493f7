"""Reading documents people write or hand over (TOML scenarios and batch files, JSON camera
paths and tables): bounded nesting, one-line errors naming the file, and for TOML the line
of every table and key (``tomllib`` keeps no positions) so that a field's error can name it.

Nesting is measured before parsing (brackets and braces outside strings and comments, in
one vectorised pass) and refused above :data:`MAX_DEPTH`, so a file nested 100 000 levels
deep is a one-line error naming its line, never a ``RecursionError``.
"""
from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path
from typing import Any, Optional

import numpy as np

from omnire.errors import ConfigError, MissingFileError, UserError

MAX_DEPTH = 64
"""Deepest nesting of arrays / tables / objects accepted (every format here needs < 10)."""

# Strings and comments of TOML; their characters are masked before brackets are counted.
_TOML_MASKED = re.compile(r'"""[\s\S]*?"""(?!")|\'\'\'[\s\S]*?\'\'\'(?!\')|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'|#[^\n]*')
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_KEY_PART = r'(?:[A-Za-z0-9_-]+|"x*"|\'x*\')'
_KEY_PATH = rf'{_KEY_PART}(?:\s*\.\s*{_KEY_PART})*'
_HEADER = re.compile(rf'^\s*(\[\[?)\s*({_KEY_PATH})\s*\]\]?\s*$')
_DEEP_KEY = re.compile(rf'{_KEY_PART}(?:[ \t]*\.[ \t]*{_KEY_PART}){{{MAX_DEPTH},}}')
_KEY = re.compile(rf'^\s*({_KEY_PATH})\s*=')


def _mask(match: re.Match) -> str:
    """A string or comment with its characters replaced, newlines and length kept (strings
    keep their quotes, so a quoted key is still seen as one)."""
    text = match.group()
    if text.startswith("#"):
        return " " * len(text)
    inner = re.sub(r"[^\n]", "x", text[1:-1])
    return text[0] + inner + text[-1]


def _depth_error(text: str, masked: str, source: str, error: type[UserError]) -> None:
    """Raise ``error`` naming the line where ``masked`` nests deeper than :data:`MAX_DEPTH`."""
    codes = np.frombuffer(masked.encode("utf-8", "surrogatepass"), dtype=np.uint8)
    step = np.zeros(len(codes), dtype=np.int32)
    step[(codes == ord("[")) | (codes == ord("{"))] = 1
    step[(codes == ord("]")) | (codes == ord("}"))] = -1
    depth = np.cumsum(step)
    if len(depth) and depth.max() > MAX_DEPTH:
        at = int(np.argmax(depth > MAX_DEPTH))
        line = masked.encode("utf-8", "surrogatepass")[:at].count(b"\n") + 1
        raise error(f"{source} line {line}: nested more than {MAX_DEPTH} levels deep (refused)")


def read_text(path: Path, what: str, error: type[UserError] = ConfigError) -> str:
    """The UTF-8 text of ``path``; a missing, unreadable or non-UTF-8 file is a one-line
    error naming it (``what``: e.g. "scenario", "batch file")."""
    path = Path(path)
    if not path.exists():
        raise MissingFileError(f"{path}: {what} not found")
    if path.is_dir():
        raise error(f"{path}: is a directory; expected a {what}")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a UTF-8 text file (byte {exc.start}: {exc.reason}); expected a {what}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None


class TomlDocument:
    """A parsed TOML text with the line of each table occurrence and of its keys.

    ``tables[(name, index)] = (header line, {key: line})``: ``name`` is the dotted table
    name ("" for the top level), ``index`` counts ``[[name]]`` occurrences from 0. Keys are
    the first part of a (dotted) key; keys of inline tables and of multi-line arrays are not
    located (their table's line is used).
    """

    def __init__(self, text: str, source: str, error: type[UserError] = ConfigError) -> None:
        self.source = source
        masked = _TOML_MASKED.sub(_mask, text)
        _depth_error(text, masked, source, error)
        deep = _DEEP_KEY.search(masked)  # a dotted key nests a table per part
        if deep:
            line = masked.count("\n", 0, deep.start()) + 1
            raise error(f"{source} line {line}: a dotted key nested more than {MAX_DEPTH} levels deep (refused)")
        try:
            self.data: dict[str, Any] = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise error(f"{source}: not valid TOML: {exc}") from None
        except RecursionError:
            raise error(f"{source}: nested too deeply (refused)") from None
        self.tables: dict[tuple[str, int], tuple[int, dict[str, int]]] = {("", 0): (1, {})}
        self._index(text, masked)

    def _index(self, text: str, masked: str) -> None:
        counts: dict[str, int] = {}
        current = ("", 0)
        depth = 0  # open brackets of a multi-line value: its lines hold no keys
        for number, (line, code) in enumerate(zip(text.split("\n"), masked.split("\n")), start=1):
            if depth == 0:
                m = _HEADER.match(code)
                if m and not _KEY.match(code):
                    name = ".".join(_key_path(line[m.start(2):m.end(2)]))
                    index = counts.get(name, 0) if m.group(1) == "[[" else 0
                    counts[name] = index + 1
                    current = (name, index)
                    self.tables[current] = (number, {})
                    continue
                k = _KEY.match(code)
                if k:
                    self.tables[current][1].setdefault(_key_path(line[k.start(1):k.end(1)])[0], number)
            depth = max(0, depth + code.count("[") + code.count("{") - code.count("]") - code.count("}"))

    def line(self, table: str = "", index: int = 0, key: Optional[str] = None) -> Optional[int]:
        """The line of ``key`` in the ``index``-th ``table`` (its header's line when ``key`` is
        None or not located; None when the table was not written as a header)."""
        found = self.tables.get((table, index))
        if found is None:
            return None
        header, keys = found
        return keys.get(key, header) if key is not None else header

    def key_lines(self, table: str = "", index: int = 0) -> dict[str, int]:
        """{key: line} of the ``index``-th ``table``."""
        return dict(self.tables.get((table, index), (None, {}))[1])


def _key_path(text: str) -> list[str]:
    """The parts of a TOML (dotted, possibly quoted) key as written."""
    data = tomllib.loads(f"{text} = 0")
    parts = []
    while isinstance(data, dict) and data:
        key = next(iter(data))
        parts.append(key)
        data = data[key]
    return parts


def parse_toml(text: str, source: str, error: type[UserError] = ConfigError) -> TomlDocument:
    """Parse TOML ``text`` (``source`` names it in errors) into a :class:`TomlDocument`."""
    return TomlDocument(text, source, error)


def load_toml(path: Path, what: str, error: type[UserError] = ConfigError) -> TomlDocument:
    """Read and parse a TOML file (``what`` names its kind in errors)."""
    return TomlDocument(read_text(path, what, error), str(path), error)


def parse_json(text: str, source: str, error: type[UserError] = ConfigError) -> Any:
    """Parse JSON ``text``; invalid JSON or nesting deeper than :data:`MAX_DEPTH` is a
    one-line ``error`` naming ``source`` (and the line)."""
    masked = _JSON_STRING.sub(lambda m: '"' + re.sub(r"[^\n]", "x", m.group()[1:-1]) + '"', text)
    _depth_error(text, masked, source, error)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{source} line {exc.lineno}: not valid JSON ({exc.msg})") from None
    except RecursionError:
        raise error(f"{source}: nested too deeply (refused)") from None


def load_json(path: Path, what: str, error: type[UserError] = ConfigError) -> Any:
    """Read and parse a JSON file (see :func:`parse_json`)."""
    return parse_json(read_text(path, what, error), str(path), error)
