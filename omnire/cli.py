"""``omnire`` entry point: dispatches to the commands in the command registry.

Plugins are loaded when the command runs (never at import), so the CLI always reflects
what is installed. ``--strict`` anywhere on the line (or OMNIRE_STRICT_PLUGINS=1) makes a
broken plugin fatal; otherwise it is reported and skipped.
"""
from __future__ import annotations

import sys
from typing import Optional

from rich.console import Console

from omnire.plugins import PluginLoadError, load_plugins


def main(argv: Optional[list[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    strict = "--strict" in argv
    argv = [a for a in argv if a != "--strict"]
    err = Console(stderr=True)
    try:
        plugins = load_plugins(strict=True if strict else None)
    except PluginLoadError as exc:
        err.print(f"[red]error:[/] {exc}")
        return 3
    if argv[:1] != ["plugins"]:
        for failure in plugins.failures:
            err.print(f"[yellow]warning:[/] {failure.describe()} (skipped; --strict makes this fatal)")
    if not argv or argv[0] in {"-h", "--help"}:
        out = Console()
        out.print("usage: omnire [--strict] <command> [args]\n\ncommands:")
        for spec in plugins.commands:
            out.print(f"  [bold]{spec.name:<10}[/] {spec.description}")
        return 0
    if argv[0] not in plugins.commands:
        err.print(f"[red]error:[/] unknown command {argv[0]!r}; commands: {', '.join(plugins.commands.names())}")
        return 2
    code = plugins.commands.get(argv[0]).main(argv[1:], plugins)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
