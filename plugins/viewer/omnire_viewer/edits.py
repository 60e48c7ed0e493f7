"""Hiding and moving actors: the viewer's panel state, turned into the simulation edit model.

The viewer keeps what its panel shows per actor (:class:`ActorEdit`: hidden, a world offset,
a turn) in an :class:`EditModel`. What is drawn never comes from there directly:
:meth:`EditModel.scenario` writes those edits as an ``omnire_sim`` :class:`Scenario` (hide =
``remove = true``; move = ``Placement(offset_world=..., yaw=...)``), on top of the scenario
file the viewer was opened with, if any, and an :class:`omnire_sim.Simulation` resolves it.
The browser objects (:func:`drawn_actors`, the runtime's ``Reconstruction.drawn``) and the
server render (``Simulation.render``) both read that one simulation, so the viewer has no edit
semantics of its own.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Optional

import torch

from omnire.api import Drawn, SceneTime
from omnire_sim import ActorEdit as SimActorEdit
from omnire_sim import Placement, Scenario, Simulation
from omnire_sim.edits import Where


@dataclasses.dataclass(frozen=True)
class ActorEdit:
    """One actor's edit as the panel shows it.

    Attributes:
        hidden: not drawn at all (the simulation's ``remove``).
        offset: (3,) metres added to the box centre, world frame (x, y, z up)
            (``Placement.offset_world``).
        yaw: degrees about the box's up axis through its centre (``Placement.yaw``).
    """

    hidden: bool = False
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0

    @property
    def is_identity(self) -> bool:
        return not self.hidden and not any(self.offset) and self.yaw == 0.0

    def placement(self) -> Placement:
        return Placement(offset_world=tuple(float(v) for v in self.offset), yaw=float(self.yaw))


def _then(first: Placement, extra: Placement) -> Placement:
    """``first`` followed by ``extra`` (a world offset and a turn about the box's up axis):
    turning about the box centre does not move it, so world offsets and yaws add."""
    return Placement(first.offset, tuple(a + b for a, b in zip(first.offset_world, extra.offset_world, strict=True)),
                     first.yaw + extra.yaw)


class EditModel:
    """Edits by actor key (a track id of the scene, or an inserted actor's id); every
    change bumps :attr:`version`, which tells the scene to re-resolve its simulation."""

    def __init__(self) -> None:
        self._edits: dict[str, ActorEdit] = {}
        self.version = 0

    def get(self, key: str) -> ActorEdit:
        return self._edits.get(key, ActorEdit())

    def set(self, key: str, edit: ActorEdit) -> None:
        if self.get(key) == edit:
            return
        if edit.is_identity:
            self._edits.pop(key, None)
        else:
            self._edits[key] = edit
        self.version += 1

    def clear(self) -> None:
        if self._edits:
            self._edits.clear()
            self.version += 1

    def __bool__(self) -> bool:
        return bool(self._edits)

    def items(self):
        return self._edits.items()

    def scenario(self, base: Optional[Scenario] = None) -> Scenario:
        """``base`` (a scenario file's edits; default none) with these edits applied:

        - a scene actor: hidden -> ``remove``; moved -> its placement followed by the
          offset and turn (on top of the base's trajectory, clock and motion, if any);
        - an inserted actor (by insert id): hidden -> the insertion dropped (the actor it
          replaces, if any, stays removed); moved -> its placement likewise.
        """
        base = base or Scenario()
        actors = {e.track: e for e in base.actors}
        inserts = {i.id: i for i in base.inserts}
        for key, edit in self._edits.items():
            where = Where("viewer", f"actor {key}")
            if key in inserts:
                ins = inserts[key]
                if edit.hidden:
                    del inserts[key]
                    if ins.replace is not None:
                        actors[ins.replace] = SimActorEdit(ins.replace, remove=True, where=where)
                else:
                    inserts[key] = dataclasses.replace(ins, placement=_then(ins.placement, edit.placement()))
            elif edit.hidden:
                actors[key] = SimActorEdit(key, remove=True, where=where)
            elif key in actors:
                if not actors[key].remove:  # removed by the scenario: nothing to move
                    old = actors[key]
                    actors[key] = dataclasses.replace(old, placement=_then(old.placement, edit.placement()))
            else:
                actors[key] = SimActorEdit(key, placement=edit.placement(), where=where)
        return dataclasses.replace(base, actors=tuple(actors.values()), inserts=tuple(inserts.values())).check()


@torch.no_grad()
def drawn_actors(sim: Simulation, time: SceneTime) -> Iterator[Drawn]:
    """Every group of actors the simulation draws at scene moment ``time`` (the runtime's
    ``Reconstruction.drawn`` with its edits, actor groups holding at least one actor), so the
    browser can place each actor by its box."""
    for group in sim.recon.drawn(time, sim):
        if group.is_actor and len(group.state.ids):
            yield group
