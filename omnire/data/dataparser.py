"""Base config and class for dataparsers (dataset readers)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from omnire.config import InstantiateConfig
from omnire.data.scene import SceneData


@dataclasses.dataclass
class DataparserConfig(InstantiateConfig):
    """Fields every dataparser shares. Subclasses add dataset-specific ones."""

    data: Path = Path(".")
    """Scene directory."""
    scale: float = 0.5
    """Image scale relative to the files on disk (intrinsics are scaled to match)."""
    holdout_every: int = 10
    """Hold out every N-th frame (all cameras) for novel-view evaluation; 0 holds out none."""


class Dataparser:
    """Reads one scene. Subclasses implement :meth:`parse`."""

    def __init__(self, config: DataparserConfig) -> None:
        self.config = config

    def parse(self) -> SceneData:
        raise NotImplementedError
