"""Where a run's schedules stand: the schedule step, from the step count or the training clock.

Every schedule of training is written in steps: the learning rates decay over the run's
length, densification grows from ``refine_start`` to ``min(refine_stop, length // 2)`` and
refines every ``refine_every``, SH bands switch on every ``sh_degree_interval``, coarse-to-fine
halves the downscale factor every ``resolution_schedule``, nodes warm up over their own step
counts. They all read one number, the *schedule step*, which this module computes:

- a step budget (``--trainer.max-steps`` without ``--trainer.max-seconds``): the schedule
  step is the training step, exactly; runs are bit-reproducible as before;
- a time budget (``--trainer.max-seconds``): the schedule is laid over the clock. Its
  length is ``--trainer.max-steps`` when given, else :data:`DEFAULT_SCHEDULE_STEPS`, and
  the schedule step is that length times the run's progress, the larger of
  step / max-steps (when given) and training seconds / max-seconds, rounded down. The run
  ends when either budget is spent, so the learning rates have decayed, densification has
  stopped at its fraction of the budget and the SH bands are on, whatever the machine's speed.

A time budget is not reproducible bit for bit: the schedule step a training step runs at
depends on how long the steps before it took, which differs between machines and between
runs on one machine. A run records its schedule (run.json ``schedule``, the ``schedule_step``
of each metrics record and the final record's ``schedule``).

Periodic events (refinement, opacity resets) fire when the schedule step passes a multiple
of their period (:func:`passed`): with a step budget that is ``step % period == 0``, as
before; on the clock one training step may pass several schedule steps (a slow machine) or
none (a fast one).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

DEFAULT_SCHEDULE_STEPS = 3000
"""The length of the schedule, in schedule steps, when ``--trainer.max-steps`` is not given
(the step budget then, or the steps the clock stands for with ``--trainer.max-seconds`` alone)."""


@dataclasses.dataclass(frozen=True)
class Schedule:
    """A run's budget and the schedule laid over it.

    Attributes:
        steps: the schedule's length in schedule steps (what learning rates decay over).
        max_steps: the step budget, or None for none (only with ``max_seconds``).
        max_seconds: the training-time budget in seconds, or 0 for none.
    """

    steps: int
    max_steps: Optional[int] = None
    max_seconds: float = 0.0

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ValueError(f"Schedule.steps {self.steps}: expected >= 1")
        if self.max_steps is None and not self.max_seconds > 0:
            raise ValueError("Schedule: expected max_steps, max_seconds or both")
        if self.max_steps is not None and self.max_steps != self.steps:
            raise ValueError(f"Schedule: steps {self.steps} must equal max_steps {self.max_steps} when given")

    @classmethod
    def of(cls, max_steps: Optional[int], max_seconds: float) -> "Schedule":
        """The schedule of ``--trainer.max-steps`` (None: not given) and ``--trainer.max-seconds`` (0: none)."""
        if max_steps is None and not max_seconds > 0:
            max_steps = DEFAULT_SCHEDULE_STEPS
        return cls(max_steps if max_steps is not None else DEFAULT_SCHEDULE_STEPS, max_steps, float(max_seconds))

    @property
    def timed(self) -> bool:
        """Whether the clock moves the schedule (a time budget is given)."""
        return self.max_seconds > 0

    def progress(self, step: int, seconds: float) -> float:
        """The fraction of the budget spent after ``step`` training steps and ``seconds`` of
        training: the larger of step / max_steps and seconds / max_seconds (those given)."""
        used = step / self.max_steps if self.max_steps is not None else 0.0
        if self.timed:
            used = max(used, seconds / self.max_seconds)
        return used

    def position(self, step: int, seconds: float) -> int:
        """The schedule step after ``step`` training steps and ``seconds`` of training. A
        step budget: ``step`` itself (``seconds`` unused). A time budget: ``floor(steps x
        progress)``, the step term exact, at most ``steps``."""
        if not self.timed:
            return step
        at = max(step if self.max_steps is not None else 0, math.floor(seconds * self.steps / self.max_seconds))
        return min(at, self.steps)

    def finished(self, step: int, seconds: float) -> bool:
        """Whether the budget is spent (the step budget or the time budget, whichever comes first)."""
        return (self.max_steps is not None and step >= self.max_steps) or (self.timed and seconds >= self.max_seconds)

    def describe(self) -> dict:
        """The schedule as recorded in run.json: ``clock`` (``steps`` or ``time``) and the budgets."""
        return {"clock": "time" if self.timed else "steps", "schedule_steps": self.steps,
                "max_steps": self.max_steps, "max_seconds": self.max_seconds}


def passed(period: int, since: int, now: int) -> bool:
    """Whether the schedule passed a multiple of ``period`` going from schedule step ``since``
    (exclusive) to ``now`` (inclusive). For consecutive steps (``since = now - 1``) this is
    ``now % period == 0``; a period <= 0 never fires."""
    return period > 0 and now // period > since // period
