"""Entry point (``omnire`` group, name ``viewer``): ``omnire view`` and the ``viewer``
training observer (``omnire train ... --trainer.observers viewer``)."""
from omnire.api import CommandSpec, TrainObserverSpec, hookimpl


def _main(argv, plugins):
    from omnire_viewer.cli import main  # imported on use: listing commands does not import viser

    return main(argv, plugins)


def _observer(trainer, options):
    from omnire_viewer.observer import ViewerObserver

    return ViewerObserver(trainer, options)


@hookimpl
def omnire_register_commands(registry) -> None:
    registry.register(CommandSpec("view", "a trained scene in the browser (viser): time slider, toggles, cameras, "
                                  "actor selection and edits, server renders", _main))


@hookimpl
def omnire_register_train_observers(registry) -> None:
    registry.register(TrainObserverSpec("viewer", "the scene live in the browser during training "
                                        "(--trainer.observer-options host=... port=..., default 127.0.0.1:8080)",
                                        _observer))
