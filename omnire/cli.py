"""``omnire`` entry point: dispatches to the commands in the command registry.

Plugins are loaded when the command runs (never at import), so the CLI always reflects
what is installed, and handed to the command (``CommandSpec.main(argv, plugins)``). ``--strict`` anywhere on the line (or OMNIRE_STRICT_PLUGINS=1) makes a
broken plugin fatal; otherwise it is reported and skipped. A :class:`~omnire.errors.UserError`
is printed as one line and exits 2; ``--debug`` shows its traceback too. Other exceptions
are bugs and keep their traceback.
"""
from __future__ import annotations

import sys
import warnings
from typing import Optional

from rich.console import Console
from rich.markup import escape

from omnire.errors import UserError
from omnire.plugins import PluginLoadError, load_plugins


def find_command(commands, argv: list[str]) -> tuple[Optional[str], list[str]]:
    """The longest registered command name that ``argv`` starts with (names may have several
    words, e.g. ``bench raster``) and the arguments after it; (None, argv) when none matches."""
    for n in range(len(argv), 0, -1):
        name = " ".join(argv[:n])
        if name in commands:
            return name, argv[n:]
    return None, argv


def print_commands(out: Console, commands, prefix: str = "") -> None:
    for spec in commands:
        if spec.name.startswith(prefix):
            out.print(f"  [bold]{spec.name:<18}[/] {spec.description}", highlight=False)


def main(argv: Optional[list[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    strict = "--strict" in argv
    debug = "--debug" in argv
    argv = [a for a in argv if a not in ("--strict", "--debug")]
    err = Console(stderr=True, highlight=False, soft_wrap=True)  # messages stay one line each
    warnings.showwarning = lambda message, *args, **kwargs: err.print(f"[yellow]warning:[/] {escape(str(message))}")
    try:
        plugins = load_plugins(strict=True if strict else None)
    except PluginLoadError as exc:
        err.print(f"[red]error:[/] {escape(str(exc))}")
        return 3
    if argv[:1] != ["plugins"]:
        for failure in plugins.failures:
            err.print(f"[yellow]warning:[/] {escape(failure.describe())} (skipped; --strict makes this fatal)")
    if not argv or argv[0] in {"-h", "--help"}:
        out = Console()
        out.print("usage: omnire [--strict] [--debug] <command> [args]\n\ncommands:")
        print_commands(out, plugins.commands)
        return 0
    name, rest = find_command(plugins.commands, argv)
    if name is None:
        group = [s for s in plugins.commands if s.name.startswith(argv[0] + " ")]
        if group:  # e.g. "omnire bench" alone: list the group
            out = Console(stderr=True)
            out.print(f"usage: omnire {argv[0]} <name> [args]\n")
            print_commands(out, plugins.commands, argv[0] + " ")
            return 2
        err.print(f"[red]error:[/] unknown command {argv[0]!r}; commands: {', '.join(plugins.commands.names())}")
        return 2
    try:
        code = plugins.commands.get(name).main(rest, plugins)
    except UserError as exc:
        if debug:
            err.print_exception()
        err.print(f"[red]error:[/] {escape(str(exc))}")
        signum = getattr(exc, "signum", None)  # training stopped by a signal: the shell's convention
        return 128 + signum if signum else 2
    except KeyboardInterrupt:
        err.print("[red]interrupted[/]")
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
