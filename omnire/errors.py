"""Error types that mean "the input is wrong", as opposed to a bug.

The CLI prints a :class:`UserError` as one line (its message names the file, field or flag
and what was expected) and exits 2; anything else is a bug and keeps its traceback.
``--debug`` shows tracebacks for everything.
"""
from __future__ import annotations


class UserError(Exception):
    """Bad input from the user: a file, a flag, a run directory, a plugin. The message names
    what is wrong and what was expected."""


class ConfigError(UserError):
    """A command-line flag or config value is invalid (the message names the field)."""


class MissingFileError(UserError, FileNotFoundError):
    """A file or directory the user pointed at (or that a dataset must hold) does not exist;
    the message names it and what it should contain."""
