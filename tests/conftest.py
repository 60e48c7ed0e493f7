"""Shared fixtures."""
import pytest

from scene_helpers import make_tiny_scene


@pytest.fixture
def tiny_scene(tmp_path):
    return make_tiny_scene(tmp_path / "scene")


def pytest_terminal_summary(terminalreporter):
    """The hostile-input suites' count (tests/hostile.py), per surface."""
    import sys

    module = sys.modules.get("hostile")
    results = getattr(module, "RESULTS", None)
    if not results:
        return
    bad = {k: sum(1 for r in results if r[k]) for k in ("traceback", "wrong", "changed")}
    surfaces: dict[str, int] = {}
    for r in results:
        surfaces[r["surface"]] = surfaces.get(r["surface"], 0) + 1
    per = ", ".join(f"{s} {n}" for s, n in sorted(surfaces.items()))
    terminalreporter.write_line(
        f"hostile inputs: {len(results)} cases tried ({per}); {bad['traceback']} produced a traceback, "
        f"{bad['wrong']} a wrong result or exit code, {bad['changed']} changed an input file")
