"""Plugin system: built-ins through the hooks, real entry-point plugins pip-installed into a
separate directory, isolation of broken plugins, strict mode, blocking by name."""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import types
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from omnire.plugins import PluginLoadError, PluginSelection, load_plugins

from plugin_site import install_on_path
from scene_helpers import DEMO_SCENE

OMNIRE = [sys.executable, "-m", "omnire.cli"]


def test_builtins_register_through_hooks():
    plugins = load_plugins(entry_points=False)
    assert "3dgs" in plugins.methods and "background" in plugins.node_types
    assert {"l1", "dssim", "depth", "opacity"} <= set(plugins.losses.names())
    assert plugins.methods.provenance("3dgs").distribution == "omnire"
    assert {"train", "eval", "render", "plugins", "bench raster", "bench train", "bench step"} <= set(plugins.commands.names())


def test_third_party_plugin_uses_only_the_public_module():
    import re

    imports = re.findall(r"^\s*(?:from|import) (omnire[\w.]*)", GOOD, re.M)
    assert imports and set(imports) == {"omnire.api"}


def _write_dist(root: Path, dist: str, module: str, body: str) -> Path:
    d = root / dist
    (d / module).mkdir(parents=True)
    (d / "pyproject.toml").write_text(textwrap.dedent(f"""
        [build-system]
        requires = ["setuptools>=64"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "{dist}"
        version = "0.0.7"
        [project.entry-points.omnire]
        {module} = "{module}.plugin"
        [tool.setuptools]
        packages = ["{module}"]
    """))
    (d / module / "__init__.py").write_text("")
    (d / module / "plugin.py").write_text(textwrap.dedent(body))
    return d


GOOD = '''
    from omnire.api import BackgroundConfig, LossSpec, MethodConfig, MethodSpec, hookimpl


    def tv(ctx):
        d = ctx.depth
        return (d[1:] - d[:-1]).abs().mean()


    @hookimpl
    def omnire_register_losses(registry):
        registry.register(LossSpec("tiny_tv", "depth total variation (test plugin)", tv))


    @hookimpl
    def omnire_register_methods(registry):
        def preset():
            return MethodConfig(nodes={"background": BackgroundConfig()}, loss_weights={"l1": 1.0, "tiny_tv": 0.01})
        registry.register(MethodSpec("tiny3dgs", "3dgs with a TV loss (test plugin)", preset))
'''

BROKEN = '''
    raise ImportError("this plugin is broken on purpose")
'''


@contextlib.contextmanager
def installed_dists(root: Path, dists: dict[str, str]):
    """Plugin distributions ``{distribution name: plugin.py body}`` (module ``omnire_test_...``
    after the name) pip-installed into a directory of their own, ``root/site``, which is on
    this process's ``sys.path`` and its subprocesses' ``PYTHONPATH`` for the duration. Not into
    the environment: the other test processes share it, and a broken plugin there fails their
    strict loads."""
    paths = [_write_dist(root, dist, dist.replace("-", "_"), body) for dist, body in dists.items()]
    site = root / "site"
    pip = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--target", str(site)]
    subprocess.run(pip + [str(d) for d in paths], check=True)
    previous = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(site), previous) if p)
    sys.path.insert(0, str(site))
    try:
        yield
    finally:
        sys.path.remove(str(site))
        if previous is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = previous


@pytest.fixture(scope="module")
def installed_test_plugins(tmp_path_factory):
    with installed_dists(tmp_path_factory.mktemp("dists"), {"omnire-test-tiny": GOOD, "omnire-test-broken": BROKEN}):
        yield


def run(args, env=None, timeout=600):
    e = dict(os.environ, COLUMNS="200", **(env or {}))
    return subprocess.run(OMNIRE + args, capture_output=True, text=True, env=e, timeout=timeout)


def test_installed_plugin_is_listed_and_broken_one_reported(installed_test_plugins):
    out = run(["plugins"])
    assert out.returncode == 0, out.stderr
    assert "tiny3dgs" in out.stdout and "tiny_tv" in out.stdout
    assert "omnire-test-tiny" in out.stdout and "0.0.7" in out.stdout
    assert "omnire-test-broken" in out.stdout and "broken on purpose" in out.stdout


def test_strict_mode_and_blocking(installed_test_plugins):
    out = run(["--strict", "plugins"])
    assert out.returncode == 3 and "omnire-test-broken" in out.stderr
    out = run(["plugins"], env={"OMNIRE_STRICT_PLUGINS": "1", "OMNIRE_DISABLE_PLUGINS": "omnire-test-broken"})
    assert out.returncode == 0 and "tiny3dgs" in out.stdout and "omnire-test-broken" not in out.stdout
    with pytest.raises(PluginLoadError, match="omnire-test-broken"):
        load_plugins(strict=True)
    plugins = load_plugins(disabled={"omnire_test_tiny"})
    assert "tiny3dgs" not in plugins.methods


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_plugin_method_selected_on_cli_despite_broken_plugin(installed_test_plugins, tmp_path):
    out = run(["train", "tiny3dgs", "pandaset", "--data", str(DEMO_SCENE), "--end-frame", "4", "--scale", "0.25",
               "--method.rasterizer", "torch", "--method.nodes.background.max-lidar-points", "3000",
               "--method.nodes.background.num-far-points", "300", "--trainer.max-steps", "3",
               "--trainer.output-dir", str(tmp_path), "--trainer.run-name", "r", "--trainer.no-progress"])
    assert out.returncode == 0, out.stdout + out.stderr
    assert "omnire-test-broken" in out.stderr  # reported, not fatal
    metrics = (tmp_path / "r" / "metrics.jsonl").read_text()
    assert "tiny_tv" in metrics


def failing_plugin_site(tmp_path: Path) -> Path:
    """A directory to put on PYTHONPATH holding the distribution omnire-test-fails, whose
    plugin module raises on import."""
    package = tmp_path / "omnire_test_fails"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "plugin.py").write_text('raise ImportError("broken on purpose")\n')
    install_on_path(tmp_path / "site", package, "omnire-test-fails", "fails")
    return tmp_path / "site"


def test_plugin_commands_get_the_cli_plugin_set(tmp_path):
    """``OMNIRE_DISABLE_PLUGINS`` and ``--strict`` reach a plugin's command: ``omnire synth``
    writes with the scene writers of the CLI's plugin set (real subprocesses, nothing generated)."""
    out_dir = tmp_path / "scene"
    out = run(["synth", "urban", str(out_dir), "--tiny", "--format", "kitti"],
              env={"OMNIRE_DISABLE_PLUGINS": "omnire-dataparser-kitti"})
    assert out.returncode == 2 and "unknown scene writer 'kitti'" in out.stderr, out.stderr
    assert not out_dir.exists()

    env = {"PYTHONPATH": str(failing_plugin_site(tmp_path))}
    out = run(["synth", "urban", str(out_dir), "--tiny", "--format", "nope"], env=env)
    assert out.returncode == 2 and "omnire-test-fails" in out.stderr and "unknown scene writer 'nope'" in out.stderr
    out = run(["--strict", "synth", "urban", str(out_dir), "--tiny", "--format", "nope"], env=env)
    assert out.returncode == 3 and "omnire-test-fails" in out.stderr and "scene writer" not in out.stderr
    assert not out_dir.exists()


def test_plugin_selection_crosses_to_a_worker_process(tmp_path):
    """What a command hands its worker process (``omnire bench render``) loads the same set:
    disabled plugins stay out, and strict mode makes a broken plugin fatal there too."""
    plugins = load_plugins(disabled={"omnire-dataparser-kitti"})
    assert plugins.selection == PluginSelection(strict=False, disabled=("omnire-dataparser-kitti",), entry_points=True)
    code = ("import json, sys; from omnire.api import PluginSelection; "
            "p = PluginSelection.from_dict(json.loads(sys.argv[1])).load(); "
            "print('kitti' in p.dataparsers, 'nuscenes' in p.dataparsers)")
    env = dict(os.environ, PYTHONPATH=str(failing_plugin_site(tmp_path)))

    def worker(selection: PluginSelection) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", code, json.dumps(selection.as_dict())], capture_output=True,
                              text=True, env=env, timeout=300)

    out = worker(plugins.selection)
    assert out.returncode == 0 and out.stdout.split() == ["False", "True"], out.stderr
    out = worker(dataclasses.replace(plugins.selection, strict=True))
    assert out.returncode != 0 and "PluginLoadError" in out.stderr and "omnire-test-fails" in out.stderr


def _module(name: str, **attrs) -> types.ModuleType:
    module = types.ModuleType(name)
    module.__dict__.update(attrs)
    return module


def test_declared_specs_register_by_kind_and_import_on_first_call(tmp_path, monkeypatch):
    """A plugin module's ``SPECS`` land in the registry of each spec's kind; a ``lazy`` target
    is imported when the spec is used, not when it is registered."""
    from omnire.api import CommandSpec, SceneWriterSpec, lazy

    (tmp_path / "lazy_target_cmd.py").write_text("def main(argv, plugins):\n    return len(argv) + 40\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lazy_target_cmd", raising=False)
    specs = (CommandSpec("lazy-cmd", "a declared command", lazy("lazy_target_cmd:main")),
             SceneWriterSpec("lazy-format", "a declared writer", lazy("lazy_target_cmd:write_scene")))
    plugins = load_plugins(entry_points=False, extra_modules=(_module("declared_plugin", SPECS=specs),))
    assert not plugins.failures
    assert plugins.commands.names().count("lazy-cmd") == 1 and "lazy-format" in plugins.scene_writers
    assert "lazy-cmd" not in plugins.scene_writers and "lazy-format" not in plugins.commands
    assert plugins.commands.provenance("lazy-cmd").distribution == "declared_plugin"
    assert "lazy_target_cmd" not in sys.modules
    assert plugins.commands.get("lazy-cmd").main(["a", "b"], plugins) == 42
    assert "lazy_target_cmd" in sys.modules
    with pytest.raises(AttributeError, match="write_scene"):  # a wrong attribute fails where it is used
        plugins.scene_writers.get("lazy-format").write(tmp_path, tmp_path)


def test_declared_specs_refuse_what_is_not_a_spec():
    """A ``SPECS`` entry that is not a spec fails its plugin (nothing of it kept), by name;
    strict mode raises; a malformed lazy target is refused when written."""
    from omnire.api import CommandSpec, LazyTargetError, lazy

    bad = _module("bad_specs", SPECS=(CommandSpec("kept-out", "d", lazy("json:dumps")), "not a spec"))
    plugins = load_plugins(entry_points=False, extra_modules=(bad,))
    assert "kept-out" not in plugins.commands
    (failure,) = plugins.failures
    assert failure.plugin == "bad_specs" and failure.stage == "registration" and "'not a spec' is not a spec" in failure.error
    with pytest.raises(PluginLoadError, match="bad_specs"):
        load_plugins(strict=True, entry_points=False, extra_modules=(bad,))
    for target in ("json.dumps", "json:", ":dumps", "json:dumps:x", "1json:dumps", None):
        with pytest.raises(LazyTargetError, match="expected 'package.module:attribute'"):
            lazy(target)


def test_loading_plugins_imports_no_command_or_reader_module():
    """Plugins are loaded for every command: registration imports none of the modules behind
    the lazy specs (commands, readers, writers, observers), in a fresh process. (The kitti,
    nuScenes and nuPlan packages import their readers in their ``__init__``.)"""
    lazy_modules = ["omnire_serve.cli", "omnire_serve.bench", "omnire_sim.cli", "omnire_sim.bench", "omnire_viewer.cli",
                    "omnire_viewer.observer", "omnire_export.cli", "omnire_compact.cli", "omnire_batch.cli",
                    "omnire_body.bench", "omnire_method.bench_skip", "omnire_synthetic.cli", "omnire_kitti.writer",
                    "omnire_nuscenes.writer", "omnire_nuplan.writer", "omnire_argoverse2.dataparser",
                    "omnire_argoverse2.writer", "omnire_rasterizer_gsplat.rasterizer",
                    "omnire_pose_mediapipe.estimator", "omnire_processed.reader", "omnire_synthetic.dataparser"]
    code = ("import json, sys; from omnire.plugins import load_plugins; p = load_plugins(); "
            "print(json.dumps([sorted(p.commands.names()), sorted(m for m in sys.modules if m.startswith('omnire_'))]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    commands, imported = json.loads(out.stdout)
    assert {"serve", "sim", "view", "export", "compact", "batch", "bench humanpose", "synth"} <= set(commands)
    assert sorted(set(lazy_modules) & set(imported)) == []
