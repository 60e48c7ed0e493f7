"""Built-in plugin: the core's own losses, the background node and the ``3dgs`` method,
registered through the same hooks as every external plugin."""
from __future__ import annotations

from omnire.hookspecs import hookimpl
from omnire.losses import BUILTIN_LOSSES
from omnire.method import MethodConfig
from omnire.nodes.background import BackgroundConfig
from omnire.registry import CommandSpec, LossSpec, MethodSpec, NodeTypeSpec


@hookimpl
def omnire_register_losses(registry) -> None:
    for name, (description, fn) in BUILTIN_LOSSES.items():
        registry.register(LossSpec(name, description, fn))


@hookimpl
def omnire_register_node_types(registry) -> None:
    registry.register(NodeTypeSpec("background", "static Gaussians in the world frame, LiDAR-initialised",
                                   BackgroundConfig))


def gs3d_method() -> MethodConfig:
    """3DGS: one static set of Gaussians for everything (moving actors become ghosts)."""
    return MethodConfig(nodes={"background": BackgroundConfig()})


@hookimpl
def omnire_register_methods(registry) -> None:
    registry.register(MethodSpec("3dgs", "static 3D Gaussian splatting (background node only)", gs3d_method))


@hookimpl
def omnire_register_commands(registry) -> None:
    from omnire import commands

    registry.register(CommandSpec("train", "train a method on a scene: omnire train <method> <dataparser> [flags]",
                                  commands.train_main))
    registry.register(CommandSpec("eval", "evaluate a run directory: omnire eval <run dir>", commands.eval_main))
    registry.register(CommandSpec("render", "render held-out or chosen frames/cameras of a run to images",
                                  commands.render_main))
    registry.register(CommandSpec("plugins", "list every registry entry and the distribution providing it",
                                  commands.plugins_main))
    registry.register(CommandSpec("bench raster", "rasterizer speed and memory across backends (JSON + table)",
                                  commands.bench_raster_main))
    registry.register(CommandSpec("bench train", "methods against each other: error against training time",
                                  commands.bench_train_main))
    registry.register(CommandSpec("bench lidar", "methods with LiDAR learning against the LiDAR baselines on "
                                  "held-out sweeps (JSON + table + error-vs-time plot)", commands.bench_lidar_main))
    registry.register(CommandSpec("bench step", "per-stage time of a training step (fused / unfused render paths)",
                                  commands.bench_step_main))

