"""The hostile-input harness shared by every suite that feeds the tools bad input.

Each case runs a real entry point (the CLI in process, so a traceback surfaces as an
exception, or a real server through a real client) and is recorded with the surface it
attacks (train, eval, sim, view, export, batch, a reader, ...). A case passes when it ends
with the expected exit and a one-line message naming the culprit (or, where a fallback is
documented, succeeds with the right result), printed no traceback and left its input files
unchanged. conftest.py prints the count per surface at the end of the session.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

from omnire.cli import main

RESULTS: list[dict] = []
"""One entry per case: surface, name, exit code, traceback?, wrong result?, changed input?"""


def digest(root: Path) -> dict[str, str]:
    """sha256 of a file, or of every file below a directory (by relative path)."""
    if root.is_file():
        return {root.name: hashlib.sha256(root.read_bytes()).hexdigest()}
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def record(surface: str, name: str, *, exit: int, traceback: str | None = None, wrong: bool = False,
           changed: bool = False) -> None:
    """Record a case run by other means than :func:`run_case` (e.g. a websocket client)."""
    RESULTS.append({"surface": surface, "case": name, "exit": exit, "traceback": traceback, "wrong": wrong,
                    "changed": changed})


def run_case(name: str, argv: list[str], capsys, inputs: list[Path], expect_exit: int = 2,
             needles: tuple[str, ...] = (), check=None, surface: str | None = None) -> tuple[int, str]:
    """Run ``omnire <argv>``; record whether it raised (a traceback), exited as expected with
    a message containing ``needles``, and left ``inputs`` unchanged. ``surface`` defaults to
    the sub-command (``argv[0]``)."""
    before = {str(p): digest(p) for p in inputs}
    traceback = None
    try:
        code = main(argv)
    except SystemExit as exc:  # tyro's own argument errors
        code = exc.code if isinstance(exc.code, int) else 2
    except Exception as exc:  # noqa: BLE001 - exactly what the suite looks for
        traceback, code = repr(exc), -1
    out = capsys.readouterr()
    text = out.out + out.err
    wrong = code != expect_exit or any(n not in text for n in needles) or (check is not None and not check())
    changed = any(digest(Path(p)) != d for p, d in before.items())
    record(surface or (argv[0] if argv else "cli"), name, exit=code, traceback=traceback, wrong=wrong,
           changed=changed)
    assert traceback is None, f"{name}: traceback {traceback}"
    assert not changed, f"{name}: an input file changed"
    assert code == expect_exit, f"{name}: exit {code}, expected {expect_exit}; output:\n{text[-2000:]}"
    for n in needles:
        assert n in text, f"{name}: {n!r} not in the output:\n{text[-2000:]}"
    assert "Traceback" not in text, f"{name}: a traceback was printed"
    assert "weights_only=False" not in text
    if check is not None:
        assert check(), f"{name}: wrong result"
    return code, text
