"""A small synthetic scene in the processed layout and the same scene written as an AV2 log
(generated once per test session, a few seconds)."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def synthetic_log(tmp_path_factory):
    """(processed scene dir, AV2 log dir) of one 8-frame, 3-camera urban scene."""
    from omnire_synthetic.generate import SynthOptions, generate

    from omnire_argoverse2.writer import write_scene

    root = tmp_path_factory.mktemp("av2_synthetic")
    processed = root / "processed"
    generate(processed, "urban", SynthOptions(frames=8, width=72, height=48, write_depth=False))
    log = root / "log"
    log.mkdir()
    write_scene(processed, log)
    return processed, log
