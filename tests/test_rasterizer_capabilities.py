"""Rasterizer capabilities are declared on the spec, checked at registration (or when a lazy
factory's object is built), reported by ``omnire plugins`` and the run log, and a backend
that implements only ``rasterize`` trains through the real CLI."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
from scene_helpers import DEMO_SCENE
from test_plugins import installed_dists, run

from omnire.errors import ConfigError
from omnire.plugins import load_plugins
from omnire.rasterization import CAPABILITIES, build_backend, describe_paths, summarize_paths
from omnire.registry import RasterizerSpec, RegistryError


class OnlyRasterize:
    name = "only"

    def rasterize(self, splats, camera, settings=None):
        raise AssertionError("not called here")


def _ok(device):
    return True, ""


def test_unknown_or_missing_capabilities_are_refused_at_registration():
    with pytest.raises(RegistryError, match="unknown capabilities \\['fast'\\]"):
        RasterizerSpec("x", "", OnlyRasterize, _ok, capabilities=frozenset({"fast"}))
    with pytest.raises(RegistryError, match="declares capabilities \\['fused_training'\\] but OnlyRasterize has no "
                                            "rasterize_gaussians_train"):
        RasterizerSpec("x", "", OnlyRasterize, _ok, capabilities=frozenset({"fused_training"}))
    # a lazy factory cannot be checked before it is built: it is when it is
    lazy = RasterizerSpec("x", "", lambda **kw: OnlyRasterize(), _ok, capabilities=frozenset({"ssim"}))
    with pytest.raises(ConfigError, match="declares capabilities \\['ssim'\\] but its object has no ssim_map"):
        build_backend(lazy)
    backend = build_backend(RasterizerSpec("x", "", OnlyRasterize, _ok))
    assert backend.capabilities == frozenset() and backend.name == "only"
    assert summarize_paths(frozenset()) == "rasterize only; missing: inference, fused_training, ssim, lidar"
    assert describe_paths(frozenset(CAPABILITIES)).count("native") == 4
    assert "lidar: missing, so LiDAR sweeps cannot be rendered" in describe_paths(frozenset())


def test_builtin_backends_declare_what_they_implement():
    plugins = load_plugins()
    assert plugins.rasterizers.get("torch").capabilities == frozenset({"lidar"})
    assert plugins.rasterizers.get("cpu").capabilities == frozenset(CAPABILITIES)
    assert plugins.rasterizers.get("gsplat").capabilities == frozenset()


MINIMAL = '''
    from omnire.api import RasterizerSpec, hookimpl


    class MinimalRasterizer:
        """Only the required contract: the reference rasterizer's rasterize, nothing else."""

        name = "minimal"

        def __init__(self):
            from omnire_rasterizer_torch.rasterizer import TorchRasterizer

            self._inner = TorchRasterizer()

        def rasterize(self, splats, camera, settings):
            return self._inner.rasterize(splats, camera, settings)


    @hookimpl
    def omnire_register_rasterizers(registry):
        registry.register(RasterizerSpec("minimal", "rasterize only (test plugin)", MinimalRasterizer,
                                         lambda device: (True, "")))
'''

OVERCLAIMING = '''
    from omnire.api import RasterizerSpec, hookimpl


    class Claims:
        name = "claims"

        def rasterize(self, splats, camera, settings):
            raise NotImplementedError


    @hookimpl
    def omnire_register_rasterizers(registry):
        registry.register(RasterizerSpec("claims", "declares a path it lacks (test plugin)", Claims,
                                         lambda device: (True, ""), capabilities=frozenset({"inference"})))
'''


@pytest.fixture(scope="module")
def installed_rasterizer_plugins(tmp_path_factory):
    with installed_dists(tmp_path_factory.mktemp("raster-dists"),
                         {"omnire-test-minraster": MINIMAL, "omnire-test-claims": OVERCLAIMING}):
        yield


def test_plugins_lists_paths_and_refuses_an_overclaiming_backend(installed_rasterizer_plugins):
    out = subprocess.run([sys.executable, "-m", "omnire.cli", "plugins"], capture_output=True, text=True,
                         env=dict(os.environ, COLUMNS="400"), timeout=600)  # wide: one table row per line
    assert out.returncode == 0, out.stderr
    line = next(l for l in out.stdout.splitlines() if "minimal" in l and "omnire-test-minraster" in l)
    assert "rasterize only; missing: inference, fused_training, ssim, lidar" in line
    cpu = next(l for l in out.stdout.splitlines() if l.strip("│ ").startswith("cpu "))
    assert "rasterize + inference, fused_training, ssim, lidar" in cpu
    torch_row = next(l for l in out.stdout.splitlines() if l.strip("│ ").startswith("torch "))
    assert "rasterize + lidar; missing: inference, fused_training, ssim" in torch_row
    assert "omnire-test-claims" in out.stdout and "Claims has no rasterize_gaussians" in out.stdout


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_a_rasterize_only_backend_trains_and_is_told_what_it_misses(installed_rasterizer_plugins, tmp_path):
    out = run(["train", "3dgs", "pandaset", "--data", str(DEMO_SCENE), "--end-frame", "4", "--scale", "0.25",
               "--method.rasterizer", "minimal", "--method.nodes.background.max-lidar-points", "3000",
               "--method.nodes.background.num-far-points", "300", "--trainer.max-steps", "3",
               "--trainer.output-dir", str(tmp_path), "--trainer.run-name", "r", "--trainer.no-progress"])
    assert out.returncode == 0, out.stdout + out.stderr
    assert "rasterizer: minimal" in out.stdout
    console = " ".join(out.stdout.split())  # the console may wrap the line
    assert "fused_training: missing, so training steps concatenate the node outputs and call rasterize" in console
    log = (tmp_path / "r" / "train.log").read_text()
    assert "rasterizer minimal: inference: missing" in log and "ssim: missing, so the D-SSIM loss uses" in log
    assert '"step": 3' in (tmp_path / "r" / "metrics.jsonl").read_text()
