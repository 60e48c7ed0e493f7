"""Output directories and files a tool writes: where they may go, what ``--overwrite`` may
replace, and writing them so that a failure leaves nothing half-written.

A tool that writes a directory leaves a marker file (:data:`MARKER`, naming the tool) in it.
``--overwrite`` replaces only a directory that holds this tool's marker and nothing of
another kind (files with suffixes the tool does not write, a run directory, another tool's
output); an empty directory may be replaced too. Never the current directory or one of its
parents, never a protected path (a run directory, its dataset) or a parent of one. Anything
else is refused with a one-line :class:`OutputError` before any work.

Writing goes through staging: :func:`staged_directory` builds the new directory beside the
output and renames it into place when complete (the old one is moved aside first and deleted
only after the rename); :func:`staged_files` writes loose files into a hidden staging folder
and moves them into place at the end. A write that fails (permission, read-only file
system, disk full, a file where a folder is expected) becomes an :class:`OutputError` naming
the path, and the staging area is removed: no partial output remains.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path
from typing import Iterable, Iterator

from omnire.errors import UserError

MARKER = ".omnire-output.json"
"""File in every output directory a tool writes: ``{"format": ..., "tool": "omnire sim"}``."""
MARKER_FORMAT = "omnire-output/1"


class OutputError(UserError):
    """An output path that may not be written or replaced, or a write that failed (the message
    names the path)."""


def _is_within(path: Path, other: Path) -> bool:
    """``path`` is ``other`` or lies below it (both resolved)."""
    return path == other or path.is_relative_to(other)


def marker_tool(folder: Path) -> str | None:
    """The tool named by ``folder``'s marker (None without a readable one)."""
    try:
        data = json.loads((folder / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data.get("tool") if isinstance(data, dict) and isinstance(data.get("tool"), str) else None


def write_marker(folder: Path, tool: str) -> None:
    """Mark ``folder`` as written by ``tool`` (what lets a later ``--overwrite`` replace it)."""
    from omnire.io.atomic import atomic_write_text

    atomic_write_text(folder / MARKER, json.dumps({"format": MARKER_FORMAT, "tool": tool}) + "\n")


def check_location(output: Path, flag: str, protect: Iterable[Path] = (), replaces: bool = True) -> None:
    """Refuse an output that is, holds or lies inside a protected path (a run directory, a
    dataset) and, when the output ``replaces`` what is there, the current directory or a
    parent of it."""
    out = Path(output).resolve()
    cwd = Path.cwd().resolve()
    if replaces and _is_within(cwd, out):
        raise OutputError(f"{flag} {output}: is the current directory or a parent of it; name a new directory")
    for p in protect:
        if p is None:
            continue
        p = Path(p).resolve()
        if _is_within(out, p) or _is_within(p, out):
            raise OutputError(f"{flag} {output}: is, holds or lies inside {p} (an input of this command); "
                              "choose a directory elsewhere")


def _foreign(folder: Path, tool: str, kinds: tuple[str, ...]) -> str | None:
    """What in ``folder`` this tool did not write (a relative path), or None."""
    for root, dirs, files in os.walk(folder):
        here = Path(root)
        for name in files:
            rel = (here / name).relative_to(folder)
            if name == MARKER:
                if here != folder:
                    return f"{rel} (another output inside it)"
                continue
            if name == "run.json":
                return f"{rel} (a run directory)"
            if not name.lower().endswith(kinds):
                return str(rel)
        for name in dirs:
            if (here / name).is_symlink():
                return f"{(here / name).relative_to(folder)} (a symbolic link)"
    return None


def check_output_dir(output: Path, tool: str, *, overwrite: bool, kinds: tuple[str, ...],
                     protect: Iterable[Path] = (), flag: str = "--output") -> None:
    """Check, before any work, that ``tool`` may write the directory ``output``: it does not
    exist, or is empty, or (with ``overwrite``) holds ``tool``'s marker and only files whose
    names end with one of ``kinds``. Raises :class:`OutputError` otherwise."""
    output = Path(output)
    check_location(output, flag, protect)
    if not output.exists() and not output.is_symlink():
        return
    if not output.is_dir() or output.is_symlink():
        raise OutputError(f"{flag} {output}: exists and is not a directory")
    try:
        empty = not any(output.iterdir())
    except OSError as exc:
        raise OutputError(f"{flag} {output}: cannot read the directory ({exc.strerror or exc})") from None
    if empty:
        return
    if not overwrite:
        raise OutputError(f"{flag} {output}: already exists; choose another directory or pass --overwrite")
    owner = marker_tool(output)
    if owner != tool:
        what = f"written by {owner}" if owner else f"not written by {tool} (no {MARKER} in it)"
        raise OutputError(f"{flag} {output}: {what}; --overwrite only replaces {tool}'s own output, so remove "
                          "it yourself or choose another directory")
    foreign = _foreign(output, tool, kinds)
    if foreign:
        raise OutputError(f"{flag} {output}: holds {foreign}, which {tool} does not write; --overwrite only "
                          "replaces the tool's own output, so remove it yourself or choose another directory")


def _describe(exc: OSError) -> str:
    return exc.strerror or str(exc)


@contextlib.contextmanager
def writing(path: Path, what: str = "cannot write", note: str = "") -> Iterator[None]:
    """Turn an :class:`OSError` inside the block into a one-line :class:`OutputError` naming
    the file that failed (or ``path``), ``what`` failed and why, then ``note``."""
    try:
        yield
    except OutputError:
        raise
    except OSError as exc:
        culprit = exc.filename if isinstance(exc.filename, str) else path
        raise OutputError(f"{culprit}: {what} ({_describe(exc)}){note}") from None


def _staging(final: Path, kind: str) -> Path:
    return final.parent / f".{final.name}.{kind}-{os.getpid()}"


def _make_parent(output: Path) -> None:
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
    except (OSError, FileExistsError) as exc:
        raise OutputError(f"{output.parent}: cannot create the output's parent directory "
                          f"({_describe(exc)})") from None


@contextlib.contextmanager
def staged_directory(output: Path, tool: str) -> Iterator[Path]:
    """Yield a fresh staging directory beside ``output``; when the block ends without error,
    mark it as ``tool``'s and rename it to ``output`` (an existing ``output``, which
    :func:`check_output_dir` allowed, is moved aside and deleted after the rename). On any
    error the staging directory is removed; an OSError becomes an :class:`OutputError`."""
    output = Path(output)
    _make_parent(output)
    staging = _staging(output, "partial")
    try:
        with writing(output, "cannot write the output", f"; nothing was written to {output}"):
            if staging.exists():
                shutil.rmtree(staging)
            staging.mkdir()
            yield staging
            write_marker(staging, tool)
            old = None
            if output.exists():
                old = _staging(output, "old")
                os.replace(output, old)
            try:
                os.replace(staging, output)
            except BaseException:
                if old is not None:
                    os.replace(old, output)
                raise
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@contextlib.contextmanager
def staged_files(folder: Path) -> Iterator[Path]:
    """Yield a hidden staging folder inside ``folder``; files written there (by their final
    relative names) are moved into ``folder`` when the block ends without error. On an error
    nothing in ``folder`` changes; an OSError becomes an :class:`OutputError`."""
    folder = Path(folder)
    made = not folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot create the output directory ({_describe(exc)})") from None
    staging = folder / f".omnire-staging-{os.getpid()}"
    try:
        with writing(folder, "cannot write the output", f"; nothing was written to {folder}"):
            staging.mkdir()
            yield staging
            moves = [(p, folder / p.relative_to(staging)) for p in sorted(staging.rglob("*")) if p.is_file()]
            for _, dest in moves:  # refuse before moving anything
                if dest.is_dir():
                    raise OutputError(f"{dest}: is a directory; cannot write the file there (nothing was written "
                                      f"to {folder})")
            created: list[Path] = []
            try:
                for path, dest in moves:
                    existed = dest.exists()
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(path, dest)
                    if not existed:
                        created.append(dest)
            except BaseException:
                for dest in created:  # take back what this write added
                    dest.unlink(missing_ok=True)
                raise
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
