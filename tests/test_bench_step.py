"""``omnire bench step``: per-stage timings of both render paths, JSON + table."""
import json

import pytest
from scene_helpers import DEMO_SCENE

from omnire.errors import ConfigError
from omnire.plugins import load_plugins

ARGS = ["--dataparser", "pandaset", "--data", str(DEMO_SCENE), "--method", "streetgs",
        "--dataparser-args=--end-frame 6 --scale 0.25",
        ("--method-args=--method.rasterizer cpu --method.nodes.background.max-lidar-points 2000 "
         "--method.nodes.background.num-far-points 200")]


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_bench_step_times_both_paths(tmp_path, capsys):
    plugins = load_plugins()
    from omnire_rasterizer_cpu import available

    if not available("cpu")[0]:
        pytest.skip("cpu rasterizer unavailable")
    main = plugins.commands.get("bench step").main
    out = tmp_path / "step.json"
    assert main([*ARGS, "--gaussians", "3000", "--at-step", "3000", "--warmup", "1", "--steps", "2",
                 "--output", str(out)], plugins) == 0
    result = json.loads(out.read_text())
    assert result["gaussians_by_node"]["background"] == 3000 and result["sh_degree"] == 3
    # real training steps: the step counter advanced once per timed or warm-up step and path
    assert result["at_step"] == 3000 and result["steps_taken_to"] == 3000 + 2 * 3
    assert set(result["paths"]) == {"fused", "unfused"}
    for stages in result["paths"].values():
        assert set(stages) == {"prepare", "nodes", "render", "lidar", "loss", "backward", "densify_stats",
                               "optimizer", "densify", "total", "total_cpu"}
        assert stages["total"]["median_ms"] > 0 and stages["render"]["median_ms"] > 0
    machine = result["machine"]  # what the numbers were measured on
    assert machine["threads"] == 1 and machine["logical_cores"] >= 1
    assert machine["copy_gb_s"] > 0 and machine["matmul_gflop_s"] > 0
    out_text = capsys.readouterr().out
    assert "backward" in out_text and "GB/s copy" in out_text
    with pytest.raises(ConfigError, match="--paths"):
        main([*ARGS, "--paths", "fast", "--steps", "1", "--output", str(out)], plugins)


def test_bench_step_times_a_trained_runs_checkpoint(tmp_path_factory, tmp_path):
    """--checkpoint: the trained Gaussians and step of a run (not the initialised ones); a run
    with other method settings is refused."""
    from scene_helpers import TINY_RUN_KEY, TINY_RUN_METHOD_ARGS, make_tiny_run

    from omnire.rundir import find_checkpoint

    root = tmp_path_factory.getbasetemp() / TINY_RUN_KEY
    run = make_tiny_run(root)
    plugins = load_plugins()
    main = plugins.commands.get("bench step").main
    method_args = " ".join(TINY_RUN_METHOD_ARGS)
    args = ["--dataparser", "processed", "--data", str(root / "scene"), "--dataparser-args=",
            "--method", "omnire", "--paths", "unfused", "--warmup", "0", "--steps", "1", "--threads", "1"]
    out = tmp_path / "step.json"
    assert main([*args, f"--method-args={method_args}", "--checkpoint", str(run), "--output", str(out)], plugins) == 0
    result = json.loads(out.read_text())
    _, _, state = find_checkpoint(run)
    trained = {k.split(".")[1]: v.shape[0] for k, v in state["model"].items()
               if k.startswith("nodes.") and k.endswith("gaussian_params.means")}
    assert result["checkpoint"] == str(run) and result["at_step"] == int(state["step"])
    assert result["gaussians_by_node"] == trained
    assert result["paths"]["unfused"]["total"]["median_ms"] > 0
    # the same data with another method setting is not the run that was trained
    other = method_args.replace("gaussians-per-person 300", "gaussians-per-person 400")
    with pytest.raises(ConfigError, match="method settings"):
        main([*args, f"--method-args={other}", "--checkpoint", str(run), "--output", str(out)], plugins)


def test_machine_probes_measure_what_they_say():
    """The probes against a slower obvious measurement of the same operations."""
    import time

    import torch

    from omnire.bench.machine import machine_info, machine_line

    info = machine_info(1)
    a = torch.rand(512, 512)
    start = time.perf_counter()
    for _ in range(3):
        a @ a
    naive_gflops = 3 * 2 * 512**3 / (time.perf_counter() - start) / 1e9
    # the probe takes the best of several larger products: at least the naive rate's order
    assert info["matmul_gflop_s"] > 0.2 * naive_gflops
    assert info["cpu"] and isinstance(info["avx2"], bool) and torch.get_num_threads() >= 1
    assert f"{info['copy_gb_s']} GB/s copy" in machine_line(info)
