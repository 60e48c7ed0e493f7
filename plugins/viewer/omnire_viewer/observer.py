"""The ``viewer`` training observer: ``omnire train ... --trainer.observers viewer`` shows the
scene live in the browser, refreshed every ``--trainer.observe-every`` steps.

The viewer never touches the model being trained: at each refresh it takes a copy of the
scene graph (the parameters once more in memory; the scene data is shared) and shows that,
so its controls (time slider, server renders) stay usable while training continues.

Address: ``--trainer.observer-options host=... port=...`` (default 127.0.0.1:8080).
"""
from __future__ import annotations

import copy

import torch

from omnire.api import Reconstruction, UserError


def snapshot(recon: Reconstruction) -> Reconstruction:
    """A copy of ``recon`` whose model tensors are independent of the original (scene data,
    method and rasterizer shared)."""
    model = recon.model
    memo = {id(model.scene): model.scene, id(model.rasterizer): model.rasterizer, id(model.method): model.method}
    with torch.no_grad():
        copied = copy.deepcopy(model, memo)
    copied.requires_grad_(False)
    return Reconstruction(recon.scene, copied, recon.method, step=recon.step)


class ViewerObserver:
    """Built by the registry's factory with the trainer; see the module docstring."""

    def __init__(self, trainer, options: dict[str, str]) -> None:
        from omnire_viewer.app import Viewer
        from omnire_viewer.scene import ViewerScene

        host = options.get("host", "127.0.0.1")
        try:
            port = int(options.get("port", "8080"))
        except ValueError:
            raise UserError(f"--trainer.observer-options port={options['port']!r}: expected a port number") from None
        self.trainer = trainer
        scene = ViewerScene(snapshot(trainer.recon))
        name = trainer.run_dir.name if trainer.run_dir is not None else "training"
        self.viewer = Viewer(scene, host, port, title=f"training {trainer.config.method_name} - {name}", verbose=False)
        print(f"viewer: {self.viewer.url} (refreshed every {trainer.config.trainer.observe_every} steps)", flush=True)

    def on_step(self, step: int, stats: dict) -> None:
        note = f"loss {stats.get('loss', float('nan')):.4f}, PSNR {stats.get('psnr', float('nan')):.2f} dB"
        self.viewer.set_recon(snapshot(self.trainer.recon), note)

    def close(self) -> None:
        self.viewer.close()
