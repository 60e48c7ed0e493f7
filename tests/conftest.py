"""Shared fixtures."""
import pytest

from scene_helpers import make_tiny_scene


@pytest.fixture
def tiny_scene(tmp_path):
    return make_tiny_scene(tmp_path / "scene")


def pytest_terminal_summary(terminalreporter):
    """The hostile-input suite's count (tests/test_hostile_inputs.py)."""
    import sys

    module = sys.modules.get("test_hostile_inputs") or next(
        (m for name, m in sys.modules.items() if name.endswith("test_hostile_inputs")), None)
    results = getattr(module, "RESULTS", None)
    if not results:
        return
    bad = {k: sum(1 for r in results if r[k]) for k in ("traceback", "wrong", "changed")}
    terminalreporter.write_line(
        f"hostile inputs: {len(results)} cases tried; {bad['traceback']} produced a traceback, "
        f"{bad['wrong']} a wrong result or exit code, {bad['changed']} changed an input file")
