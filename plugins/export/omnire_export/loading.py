"""Loading a trained scene with little memory: :meth:`Reconstruction.from_run` with
``read_only=True`` memory-maps the checkpoint (``torch.load(mmap=True)``: nothing is read
until used, the optimiser state never is) and the scene graph adopts the mapped model
tensors instead of copying them (``load_state_dict(assign=True)``). The parameters then
occupy their size once (as file pages the kernel may drop and re-read) while the export
streams them out."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from omnire.api import Reconstruction, RunDirectoryError


def load_reconstruction(run_dir: Path, plugins, checkpoint: Optional[Path] = None) -> Reconstruction:
    """The trained scene of ``run_dir`` (its newest intact checkpoint, or ``checkpoint``) on
    the CPU, its model tensors memory-mapped from the checkpoint file (read-only use)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirectoryError(f"{run_dir}: no such run directory")
    return Reconstruction.from_run(run_dir, plugins, checkpoint, read_only=True)
