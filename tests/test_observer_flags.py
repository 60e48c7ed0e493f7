"""``--<observer>`` on ``omnire train`` is short for ``--trainer.observers <observer>``."""
from __future__ import annotations

import types

from omnire.plugins import load_plugins
from omnire.registry import TrainObserverSpec
from omnire.runconfig import expand_observer_flags, parse_train_args
from omnire.hookspecs import hookimpl
from scene_helpers import DEMO_SCENE


def test_expand_observer_flags():
    names = ["viewer", "logger"]
    assert expand_observer_flags(["omnire", "pandaset", "--data", "d"], names) == ["omnire", "pandaset", "--data", "d"]
    assert expand_observer_flags(["omnire", "--viewer", "pandaset"], names) == [
        "omnire", "pandaset", "--trainer.observers", "viewer"]
    # merged into an explicit list, no duplicates, flags after the list kept
    assert expand_observer_flags(["m", "--trainer.observers", "logger", "--viewer", "--trainer.observe-every", "5",
                                  "--viewer"], names) == [
        "m", "--trainer.observers", "logger", "viewer", "--trainer.observe-every", "5"]
    assert expand_observer_flags(["m", "--trainer.observers", "viewer", "--viewer"], names) == [
        "m", "--trainer.observers", "viewer"]
    assert expand_observer_flags(["m", "--viewers"], names) == ["m", "--viewers"]  # exact flags only


def test_observer_flag_reaches_the_trainer_config():
    # a real plugin set plus one observer registered by a module of this test
    module = types.ModuleType("watch_plugin")

    @hookimpl
    def omnire_register_train_observers(registry):
        registry.register(TrainObserverSpec("watch", "test observer", lambda trainer, options: None))

    module.omnire_register_train_observers = omnire_register_train_observers
    plugins = load_plugins(extra_modules=(module,))
    cfg = parse_train_args(["3dgs", "pandaset", "--data", str(DEMO_SCENE), "--watch", "--trainer.observe-every", "7"],
                           plugins)
    assert cfg.trainer.observers == ("watch",) and cfg.trainer.observe_every == 7
