"""Console output shared by the commands."""
from __future__ import annotations

import sys

from rich.console import Console

PIPE_WIDTH = 200
"""Columns used when output is not a terminal, so tables are never squeezed into 80."""


def output_console(stderr: bool = False) -> Console:
    """A rich console that prints tables in full when writing to a pipe or a file."""
    stream = sys.stderr if stderr else sys.stdout
    return Console(stderr=stderr, width=None if stream.isatty() else PIPE_WIDTH, highlight=False)
