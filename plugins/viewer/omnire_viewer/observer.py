"""The ``viewer`` training observer: ``omnire train ... --trainer.observers viewer`` shows the
scene live in the browser, refreshed every ``--trainer.observe-every`` steps.

The viewer never touches the model being trained: at each refresh it takes a copy of the
scene graph (the parameters once more in memory; the scene data is shared) and shows that,
so its controls (time slider, server renders) stay usable while training continues.

Address: ``--trainer.observer-options host=... port=...`` (default 127.0.0.1:8080).
"""
from __future__ import annotations

from omnire.api import UserError


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
        scene = ViewerScene(trainer.recon.snapshot())
        name = trainer.run_dir.name if trainer.run_dir is not None else "training"
        self.viewer = Viewer(scene, host, port, title=f"training {trainer.config.method_name} - {name}", verbose=False)
        print(f"viewer: {self.viewer.url} (refreshed every {trainer.config.trainer.observe_every} steps)", flush=True)

    def on_step(self, step: int, stats: dict) -> None:
        note = f"loss {stats.get('loss', float('nan')):.4f}, PSNR {stats.get('psnr', float('nan')):.2f} dB"
        self.viewer.set_recon(self.trainer.recon.snapshot(), note)

    def close(self) -> None:
        self.viewer.close()
