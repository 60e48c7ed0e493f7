"""Loading a trained scene with little memory.

:meth:`Reconstruction.from_run` reads the whole checkpoint (model, the optimiser's two Adam
moments, densification statistics) into memory and copies the model tensors into the scene
graph: about four times the Gaussian parameters at its peak. An export only reads the
parameters, so here the checkpoint is memory-mapped (``torch.load(mmap=True)``: nothing is
read until used, the optimiser state never is) and the scene graph adopts the mapped model
tensors instead of copying them (``load_state_dict(assign=True)``). The parameters then
occupy their size once (as file pages the kernel may drop and re-read) while the export
streams them out.

Everything else follows :meth:`Reconstruction.from_run` / :meth:`Reconstruction.restore`
(same run directory checks, newest intact checkpoint, recorded arguments and node
assignment).
"""
from __future__ import annotations

import os
import pickle
import warnings
from pathlib import Path
from typing import Optional

import torch

from omnire.api import Reconstruction
from omnire.model import SceneModel, enabled_node_specs
from omnire.rasterization import select_rasterizer
from omnire.rundir import CHECKPOINT_KEYS, CheckpointError, RunDirectory, RunDirectoryError
from omnire.runtime import parse_recorded_args


def load_mapped_checkpoint(path: Path) -> dict:
    """A checkpoint's state, memory-mapped (tensors are read on first use). Raises
    :class:`CheckpointError` naming the file when it is empty, damaged, unsafe or not a
    checkpoint."""
    path = Path(path)
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read checkpoint ({exc.strerror or exc})") from None
    if size == 0:
        raise CheckpointError(f"{path}: empty checkpoint file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError:
        raise CheckpointError(f"{path}: refused as unsafe (it holds objects other than tensors and plain "
                              "data)") from None
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged file
        first = str(exc).splitlines()[0] if str(exc) else "unreadable"
        raise CheckpointError(f"{path}: damaged or truncated checkpoint ({type(exc).__name__}: {first})") from None
    if not isinstance(state, dict) or any(k not in state for k in CHECKPOINT_KEYS):
        raise CheckpointError(f"{path}: not an omnire checkpoint (expected a dict with {list(CHECKPOINT_KEYS)})")
    return state


def newest_checkpoint(run: RunDirectory) -> tuple[Path, dict]:
    """The newest intact checkpoint of ``run`` (damaged ones are skipped with a warning)."""
    ckpts = run.checkpoints()
    if not ckpts:
        raise RunDirectoryError(f"{run.path}: no checkpoints/step-*.pt inside (the run saved no checkpoint)")
    problems = []
    for _, path in reversed(ckpts):
        try:
            return path, load_mapped_checkpoint(path)
        except CheckpointError as exc:
            problems.append(str(exc))
            warnings.warn(f"{exc}; trying an older checkpoint", stacklevel=2)
    raise RunDirectoryError(f"{run.path}: no intact checkpoint: " + "; ".join(problems))


def load_reconstruction(run_dir: Path, plugins, checkpoint: Optional[Path] = None) -> Reconstruction:
    """The trained scene of ``run_dir`` (its newest intact checkpoint, or ``checkpoint``) on
    the CPU, its model tensors memory-mapped from the checkpoint file (read-only use)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirectoryError(f"{run_dir}: no such run directory")
    run = RunDirectory(run_dir)
    info = run.read_info()
    config = parse_recorded_args(info, plugins)
    if checkpoint is not None:
        path, state = Path(checkpoint), load_mapped_checkpoint(checkpoint)
    else:
        path, state = newest_checkpoint(run)
    device = torch.device("cpu")
    scene = config.dataparser.setup().parse().validate()
    specs = enabled_node_specs(config.method, plugins.node_types)
    rasterizer = select_rasterizer(plugins, config.method.rasterizer, device)
    model = SceneModel(config.method, scene, specs, None, rasterizer, device, assignment=info.node_assignment,
                       restoring=True)
    for name, node in model.nodes.items():
        node.prepare_load(state["model"], prefix=f"nodes.{name}.")
    model.load_state_dict(state["model"], assign=True)
    model.requires_grad_(False)
    recon = Reconstruction(scene, model, config.method, step=int(state["step"]))
    recon.run_info, recon.config, recon.run_dir, recon.checkpoint = info, config, run, path
    return recon
