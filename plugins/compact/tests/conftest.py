"""Fixtures: the tiny trained OmniRe run of ``scene_helpers.make_tiny_run`` (one per test
session, shared with the other plugins' tests)."""
from __future__ import annotations

import pytest

from scene_helpers import TINY_RUN_KEY, make_tiny_run


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    return make_tiny_run(tmp_path_factory.getbasetemp() / TINY_RUN_KEY)
