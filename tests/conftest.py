"""Shared fixtures."""
import pytest

from scene_helpers import make_tiny_scene


@pytest.fixture
def tiny_scene(tmp_path):
    return make_tiny_scene(tmp_path / "scene")
