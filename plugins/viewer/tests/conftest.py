"""Fixtures: the tiny trained OmniRe run of ``scene_helpers.make_tiny_run``, made once per
test session and shared with the other plugins' tests, and its twin that learned LiDAR
(``make_tiny_lidar_run``)."""
from __future__ import annotations

import pytest

from scene_helpers import TINY_LIDAR_RUN_KEY, TINY_RUN_KEY, make_tiny_lidar_run, make_tiny_run


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    return make_tiny_run(tmp_path_factory.getbasetemp() / TINY_RUN_KEY)


@pytest.fixture(scope="session")
def tiny_lidar_run(tmp_path_factory):
    return make_tiny_lidar_run(tmp_path_factory.getbasetemp() / TINY_LIDAR_RUN_KEY)


@pytest.fixture(scope="session")
def plugins():
    from omnire.plugins import load_plugins

    return load_plugins()
