"""Config base: dataclasses with a ``_target`` class and ``setup()`` (nerfstudio style).

Every field carries a docstring below it; tyro turns those into ``--help`` text. Fields
whose names start with ``_`` are not exposed on the command line.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Type


@dataclasses.dataclass
class InstantiateConfig:
    """A config that knows which class it configures: ``config.setup(**kw)`` builds it."""

    _target: Type = dataclasses.field(default_factory=lambda: object)

    def setup(self, **kwargs: Any) -> Any:
        return self._target(self, **kwargs)


def to_dict(config: Any) -> Any:
    """JSON-friendly view of a (nested) config, for run directories."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        out = {"__type__": f"{type(config).__module__}.{type(config).__qualname__}"}
        for f in dataclasses.fields(config):
            if f.name.startswith("_"):
                continue
            out[f.name] = to_dict(getattr(config, f.name))
        return out
    if isinstance(config, (list, tuple)):
        return [to_dict(v) for v in config]
    if isinstance(config, dict):
        return {str(k): to_dict(v) for k, v in config.items()}
    if isinstance(config, (str, int, float, bool)) or config is None:
        return config
    return str(config)
