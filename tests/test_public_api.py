"""The plugin boundary: plugins import the core through its public modules only, plugin
dependencies are declared and point one way (the import contracts of pyproject.toml, run by
``lint-imports``), and a third-party plugin written against ``omnire.api`` alone is checked by
those contracts and loaded by the real plugin loader (a real ``omnire`` subprocess)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import grimp
import pytest

from plugin_site import install_on_path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = Path(__file__).parent / "plugin_example" / "omnire_example"
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"
OMNIRE = [sys.executable, "-m", "omnire.cli"]
CONFIG = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]


def plugin_distributions() -> dict[str, dict]:
    """Package name -> its distribution's [project] table, for every plugin and dataparser."""
    out = {}
    for pyproject in sorted([*REPO.glob("plugins/*/pyproject.toml"), *REPO.glob("dataparsers/*/pyproject.toml")]):
        packages = [p.name for p in pyproject.parent.glob("omnire_*") if (p / "__init__.py").is_file()]
        assert len(packages) == 1, f"{pyproject.parent}: expected one omnire_* package, found {packages}"
        out[packages[0]] = tomllib.loads(pyproject.read_text())["project"]
    return out


def contract(contract_id: str) -> dict:
    return next(c for c in CONFIG["contracts"] if c.get("id") == contract_id)


def test_every_plugin_package_is_under_the_contracts():
    packages = set(plugin_distributions())
    assert set(CONFIG["root_packages"]) == packages | {"omnire"}
    layered = {name.strip() for layer in contract("plugin-layers")["layers"] for name in layer.split("|")}
    assert layered == packages
    assert set(contract("core-independent")["forbidden_modules"]) == packages
    assert set(contract("plugin-modules-acyclic")["ancestors"]) == packages


def test_plugin_to_plugin_imports_are_declared_dependencies():
    """Every import of another plugin's package (at any depth, deferred imports included) is a
    dependency of the importer's distribution, or of one of its non-test extras."""
    dists = plugin_distributions()
    graph = grimp.build_graph(*dists, cache_dir=None)
    undeclared = []
    for importer, project in dists.items():
        declared = {re.split(r"[<>=!~\[ ;]", d, maxsplit=1)[0] for d in project.get("dependencies", [])}
        for extra, deps in project.get("optional-dependencies", {}).items():
            if extra != "test":
                declared |= {re.split(r"[<>=!~\[ ;]", d, maxsplit=1)[0] for d in deps}
        for imported in dists:
            if imported != importer and graph.direct_import_exists(importer=importer, imported=imported,
                                                                  as_packages=True):
                if dists[imported]["name"] not in declared:
                    undeclared.append(f"{importer} imports {imported} without declaring {dists[imported]['name']}")
    assert not undeclared, "\n".join(undeclared)


def test_repository_keeps_the_import_contracts():
    out = subprocess.run([str(LINT_IMPORTS), "--no-cache"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"Contracts: {len(CONFIG['contracts'])} kept, 0 broken." in out.stdout


def install_example(site: Path) -> None:
    install_on_path(site, EXAMPLE, "omnire-example", "example")


def lint_example(site: Path, cwd: Path) -> subprocess.CompletedProcess:
    """The public-API contract of pyproject.toml, applied to the core and ``omnire_example``."""
    public = contract("public-api")

    def toml_list(values) -> str:
        return "[" + ", ".join(json.dumps(v) for v in values) + "]"

    config = cwd / "importlinter.toml"
    config.write_text("\n".join([
        "[tool.importlinter]",
        f"root_packages = {toml_list(['omnire', 'omnire_example'])}",
        "[[tool.importlinter.contracts]]",
        f"name = {json.dumps(public['name'])}",
        f"type = {json.dumps(public['type'])}",
        f"protected_modules = {toml_list(public['protected_modules'])}",
        f"allowed_importers = {toml_list(public['allowed_importers'])}",
        f"ignore_imports = {toml_list(public['ignore_imports'])}",
        'unmatched_ignore_imports_alerting = "none"',  # the example does not use omnire.command_api
    ]) + "\n")
    env = dict(os.environ, PYTHONPATH=str(site))
    return subprocess.run([str(LINT_IMPORTS), str(config), "--no-cache"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_third_party_plugin_is_checked_by_the_public_api_contract(tmp_path):
    site = tmp_path / "site"
    install_example(site)
    out = lint_example(site, tmp_path)
    assert out.returncode == 0 and "KEPT" in out.stdout, out.stdout + out.stderr

    # the same plugin reaching past omnire.api breaks the contract, naming the import
    (site / "omnire_example" / "internals.py").write_text("from omnire.registry import Registry  # noqa: F401\n")
    out = lint_example(site, tmp_path)
    assert out.returncode == 1 and "BROKEN" in out.stdout, out.stdout + out.stderr
    assert "omnire_example.internals -> omnire.registry" in out.stdout


def test_third_party_plugin_is_loaded_by_the_plugin_loader(tmp_path):
    site = tmp_path / "site"
    install_example(site)
    env = dict(os.environ, PYTHONPATH=str(site), COLUMNS="200")
    out = subprocess.run([*OMNIRE, "--strict", "plugins"], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "example_depth_smoothness" in out.stdout and "omnire-example" in out.stdout
    env["OMNIRE_DISABLE_PLUGINS"] = "omnire-example"
    out = subprocess.run([*OMNIRE, "plugins"], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0 and "example_depth_smoothness" not in out.stdout


def test_third_party_loss_runs_from_the_registry(tmp_path, monkeypatch):
    """Loaded in this process through its entry point, the loss computes what it says: the
    mean absolute neighbour difference of the depth, over the scene's pixels."""
    import torch

    from omnire.api import LossContext
    from omnire.plugins import load_plugins

    site = tmp_path / "site"
    install_example(site)
    monkeypatch.syspath_prepend(str(site))
    plugins = load_plugins(strict=True)
    assert plugins.losses.provenance("example_depth_smoothness").distribution == "omnire-example"
    fn = plugins.losses.get("example_depth_smoothness").fn
    depth = torch.arange(12.0).reshape(3, 4, 1)  # +1 along x, +4 along y
    ctx = LossContext(rgb=torch.zeros(3, 4, 3), depth=depth, alpha=torch.ones(3, 4, 1), target=torch.zeros(3, 4, 3))
    expected = (9 * 1.0 + 8 * 4.0) / (9 + 8)
    assert float(fn(ctx)) == pytest.approx(expected)
