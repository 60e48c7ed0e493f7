"""Callables named by ``"module:attribute"``, imported on first call, for registry specs.

Plugins are loaded for every ``omnire`` command, so what a spec points to (a command's
``main``, a reader's config class, a writer) should not be imported when it is registered:
``lazy("omnire_kitti.writer:write_scene")`` stands in for the function and imports its module
only when it is called.
"""
from __future__ import annotations

import importlib
import re
from typing import Any, Callable

from omnire.errors import UserError

_TARGET = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*")


class LazyTargetError(UserError):
    """A lazy target is not of the form ``"package.module:attribute"``."""


class Lazy:
    """The callable at ``module:attribute``, imported on the first call and kept."""

    def __init__(self, target: str) -> None:
        if not isinstance(target, str) or not _TARGET.fullmatch(target):
            raise LazyTargetError(f"lazy target {target!r}: expected 'package.module:attribute'")
        self.target = target
        self._resolved: Callable[..., Any] | None = None

    def resolve(self) -> Callable[..., Any]:
        """The callable itself (importing its module the first time)."""
        if self._resolved is None:
            module, attribute = self.target.split(":")
            self._resolved = getattr(importlib.import_module(module), attribute)
        return self._resolved

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.resolve()(*args, **kwargs)

    def __repr__(self) -> str:
        return f"lazy({self.target!r})"


def lazy(target: str) -> Lazy:
    """A callable standing in for ``target`` (``"package.module:attribute"``) that imports it on
    its first call and forwards every call to it, e.g. a ``CommandSpec``'s ``main``."""
    return Lazy(target)
