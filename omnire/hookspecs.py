"""pluggy hook specifications: how a plugin fills the registries.

A plugin is a module (found through the ``omnire`` entry-point group) holding functions
decorated with :data:`hookimpl` named like the hooks of :class:`HookSpecs`. Each hook receives the
registry to fill; return values are ignored. The hooks are made here from
:data:`omnire.registry.REGISTRY_KINDS`, one ``omnire_register_<kind>(registry)`` per kind (its
docstring says what it registers). A plugin that only declares specs may list them in a
module-level ``SPECS`` tuple instead: the loader registers each into the registry of its kind.
Plugin authors import everything they need from :mod:`omnire.api`.

Example (in ``my_plugin/plugin.py``, with ``[project.entry-points.omnire] my = "my_plugin.plugin"``)::

    from omnire.api import LossSpec, hookimpl

    @hookimpl
    def omnire_register_losses(registry):
        registry.register(LossSpec("tv", "total variation of depth", tv_loss))

or, declared (callables named ``"module:attribute"`` are imported on first call)::

    from omnire.api import CommandSpec, lazy

    SPECS = (CommandSpec("mine", "what it does", lazy("my_plugin.cli:main")),)
"""
from __future__ import annotations

from typing import Any, Callable

import pluggy

from omnire.registry import REGISTRY_KINDS, Registry, RegistryKind

PROJECT = "omnire"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


def _hook(kind: RegistryKind) -> Callable[[Registry[Any]], None]:
    def register(registry: Registry[Any]) -> None:
        ...  # a specification has no body: pluggy checks implementations against its signature

    register.__name__ = register.__qualname__ = kind.hook
    register.__doc__ = f"Register {kind.registers}: ``registry.register({kind.spec.__name__}(...))``."
    return hookspec(register)


class HookSpecs:
    """The hook specifications, one per registry kind (what the plugin manager is given)."""


for _kind in REGISTRY_KINDS:
    setattr(HookSpecs, _kind.hook, staticmethod(_hook(_kind)))
