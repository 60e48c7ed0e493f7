"""Shared fixtures."""
import pytest

from scene_helpers import make_tiny_scene


@pytest.fixture
def tiny_scene(tmp_path):
    return make_tiny_scene(tmp_path / "scene")


_WORKER_HOSTILE_RESULTS = pytest.StashKey[list]()
"""The hostile-input cases of finished pytest-xdist workers (in the controller)."""


def _hostile_results() -> list[dict]:
    import sys

    return list(getattr(sys.modules.get("hostile"), "RESULTS", None) or [])


def pytest_sessionfinish(session):
    """In a pytest-xdist worker: hand this worker's hostile-input cases to the controller."""
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:
        workeroutput["hostile_results"] = _hostile_results()


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """In the pytest-xdist controller: collect a finished worker's hostile-input cases."""
    node.config.stash.setdefault(_WORKER_HOSTILE_RESULTS, []).extend(
        getattr(node, "workeroutput", {}).get("hostile_results", []))


def pytest_terminal_summary(terminalreporter, config):
    """The hostile-input suites' count (tests/hostile.py), per surface, over every worker."""
    results = _hostile_results() + config.stash.get(_WORKER_HOSTILE_RESULTS, [])
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
