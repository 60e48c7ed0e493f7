"""Entry point (``omnire`` group, name ``viewer``): ``omnire view`` and the ``viewer``
training observer (``omnire train ... --trainer.observers viewer``). Both are imported on use:
listing commands does not import viser."""
from omnire.api import CommandSpec, TrainObserverSpec, lazy

SPECS = (
    CommandSpec("view", "a trained scene in the browser (viser): time slider, toggles, cameras, actor selection "
                "and edits, server renders", lazy("omnire_viewer.cli:main")),
    TrainObserverSpec("viewer", "the scene live in the browser during training (--trainer.observer-options "
                      "host=... port=..., default 127.0.0.1:8080)", lazy("omnire_viewer.observer:ViewerObserver")),
)
