"""Schedules on a step or a time budget (omnire/schedule.py): the schedule step itself, a
step budget trains exactly as the step-indexed trainer did, and ``--trainer.max-seconds``
alone completes every schedule (learning rates decayed, densification stopped at its
fraction of the budget, SH degree of the schedule) within the budget plus one step, on a
fast and on a slowed step, resumably; OmniRe on ``omnire synth urban --tiny``."""
import json
import math
import time

import pytest
import torch

from omnire.optim import exponential_lr
from omnire.plugins import load_plugins
from omnire.resolution import downscale_factor
from omnire.runconfig import parse_train_args
from omnire.runtime import Reconstruction
from omnire.schedule import DEFAULT_SCHEDULE_STEPS, Schedule, passed
from omnire.trainer import Trainer

from scene_helpers import TINY_RUN_METHOD_ARGS

# every schedule within a dozen steps: growth until 6 (half of 12), a reset at 4, SH bands
# every 3, half resolution for 4 steps, deformable warm-up of 4, the lrs decaying over 12
FAST_SCHEDULES = ["--method.densify.refine-start", "2", "--method.densify.refine-every", "3",
                  "--method.densify.reset-every", "4", "--method.densify.grad-threshold", "1e-5",
                  "--method.sh-degree-interval", "3", "--method.num-downscales", "1",
                  "--method.resolution-schedule", "4", "--method.nodes.deformable.warmup-steps", "4",
                  # the reference below predates pruning when growth stops (tested in test_trainer.py)
                  "--method.densify.keep-after-growth", "1"]
# the native rasterizer where built (steps of ~40 ms, not seconds) and neutral body poses (no pose estimation)
FAST_BUILD = ["--method.rasterizer", "auto", "--method.nodes.smpl.pose-source", "neutral"]
BUDGET = 3.0  # seconds of training of the time-budget runs (some 20-60 steps of the tiny scene)
# the default 3000-step schedule on the clock; refinement every 2 training steps (the
# statistics window counts training steps), growing easily
TIMED_METHOD = ["--method.densify.refine-every", "2", "--method.densify.grad-threshold", "1e-5"]


# ---------------------------------------------------------------------------- the schedule step
def test_a_step_budget_is_the_step_count_whatever_the_clock():
    sched = Schedule.of(40, 0.0)
    assert (sched.steps, sched.max_steps, sched.timed) == (40, 40, False)
    for step in range(0, 60):
        for seconds in (0.0, 1.0, 1e9):
            assert sched.position(step, seconds) == step
            assert sched.finished(step, seconds) == (step >= 40)


def test_the_clock_moves_a_time_budget():
    alone = Schedule.of(None, 10.0)  # the default length laid over 10 s, no step limit
    assert (alone.steps, alone.max_steps, alone.timed) == (DEFAULT_SCHEDULE_STEPS, None, True)
    assert alone.position(10**6, 2.5) == DEFAULT_SCHEDULE_STEPS // 4  # steps do not count
    assert alone.position(0, 9.9999) == DEFAULT_SCHEDULE_STEPS - 1 and alone.position(0, 50.0) == alone.steps
    assert not alone.finished(10**6, 9.99) and alone.finished(0, 10.0)
    both = Schedule.of(100, 10.0)  # whichever budget is spent first
    assert both.position(30, 1.0) == 30 and both.position(30, 5.0) == 50 and both.position(30, 5.05) == 50
    assert both.finished(100, 0.5) and both.finished(3, 10.0) and not both.finished(99, 9.9)
    assert both.progress(30, 5.0) == 0.5
    for step in range(0, 100, 7):  # the floor of steps x progress, the step term exact
        for seconds in (0.0, 0.37, 3.3, 9.99):
            expected = min(100, math.floor(max(step / 100, seconds / 10.0) * 100 + 1e-9))
            assert both.position(step, seconds) == expected, (step, seconds)
    assert Schedule.of(None, 0.0).max_steps == DEFAULT_SCHEDULE_STEPS  # no budget given: 3000 steps


@pytest.mark.parametrize("period", [1, 3, 100])
def test_passed_is_the_modulo_for_consecutive_steps_and_any_multiple_in_between(period):
    for now in range(0, 400):
        assert passed(period, now - 1, now) == (now % period == 0)
        for since in range(max(-1, now - 250), now + 1):
            brute = any(m % period == 0 for m in range(since + 1, now + 1))
            assert passed(period, since, now) == brute, (since, now)
    assert not passed(0, 0, 10**6) and not passed(-5, 0, 10)


# ---------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """``omnire synth urban --tiny`` with one camera (background, cars, people, sky)."""
    root = tmp_path_factory.mktemp("schedule")
    plugins = load_plugins()
    assert plugins.commands.get("synth").main(["urban", str(root / "scene"), "--tiny", "--num-cameras", "1"],
                                              plugins) in (0, None)
    return root, plugins


def trainer_of(synth, name, flags, cls=Trainer, method=()):
    root, plugins = synth
    torch.set_num_threads(1)
    argv = ["omnire", "processed", "--data", str(root / "scene"), "--trainer.output-dir", str(root / "runs"),
            "--trainer.run-name", name, "--trainer.no-progress", "--trainer.eval-train-views", "1",
            "--trainer.log-every", "1", *TINY_RUN_METHOD_ARGS, *FAST_BUILD, *method, *flags]
    return cls(parse_train_args(argv, plugins), plugins, argv=argv)


class StepIndexedTrainer(Trainer):
    """The trainer's stages as they were before time budgets: every schedule (SH degree,
    resolution, node warm-ups, learning rates, densification) read at the step count."""

    def sh_degree(self):
        return self.recon.sh_degree(self.step)

    def resolution_factor(self, step=None):
        m = self.config.method
        return downscale_factor(self.step, m.num_downscales, m.resolution_schedule)

    def stage_nodes(self, s):
        s.parts = self.recon.node_outputs(self.recon.drawn(s.time), s.camera, s.time, self.step)

    def stage_render(self, s):
        s.result = self.recon.render_outputs(s.parts, s.camera, s.time, step=self.step)

    def stage_optimizer(self, s):
        self.optimizers.step(self.step)
        self.optimizers.zero_grad()
        self.recon.step += 1

    def stage_densify(self, s):
        self.strategy.step(self.model.gaussian_nodes(), self.optimizers, self.step)


def assert_equal_trees(a, b, path="") -> None:
    """Nested dicts / lists of tensors and plain values equal, tensors bit for bit."""
    if torch.is_tensor(a):
        assert torch.equal(a, b), path
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            assert_equal_trees(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_equal_trees(x, y, f"{path}[{i}]")
    else:
        assert a == b, path


def assert_identical(a: Trainer, b: Trainer) -> None:
    """Parameters, buffers, Adam moments and learning rates, densification statistics, RNGs."""
    sa, sb = a.state_dict(), b.state_dict()
    for key in ("step", "model", "optimizers", "strategy", "rng_torch", "rng_sampler"):
        assert_equal_trees(sa[key], sb[key], key)


def test_a_step_budget_trains_bit_identically_to_the_step_indexed_trainer(synth):
    steps = ["--trainer.max-steps", "12"]
    trained = trainer_of(synth, "steps", steps, method=FAST_SCHEDULES)
    n0 = trained.model.num_gaussians()
    trained.train()
    reference = trainer_of(synth, "reference", steps, StepIndexedTrainer, FAST_SCHEDULES)
    for _ in range(12):
        reference.train_step()
    assert trained.step == reference.step == 12 and trained.recon.schedule_step == 12
    assert trained.model.num_gaussians() != n0  # densification ran (grown and/or pruned)
    assert_identical(trained, reference)
    # the clock never leads a budget of a million seconds: the clock's path, the same run
    clocked = trainer_of(synth, "clocked", [*steps, "--trainer.max-seconds", "1e6"], method=FAST_SCHEDULES)
    clocked.train()
    assert_identical(trained, clocked)
    record = json.loads((trained.run_dir / "run.json").read_text())["schedule"]
    assert record["clock"] == "steps" and record["steps"] == 12 and record["densify_stop_schedule_step"] == 6
    assert record["densify_stopped"]["step"] == 6


class SlowTrainer(Trainer):
    """A slower machine: each step sleeps inside its timed stages."""

    def stage_render(self, s):
        time.sleep(0.06)
        super().stage_render(s)


@pytest.fixture(scope="module")
def timed(synth):
    """Two runs on --trainer.max-seconds alone, a fast and a slowed step (a checkpoint every 4)."""
    runs = {}
    for name, cls in (("fast", Trainer), ("slow", SlowTrainer)):
        runs[name] = trainer_of(synth, name, ["--trainer.max-seconds", str(BUDGET), "--trainer.checkpoint-every", "4"],
                                cls, TIMED_METHOD)
        if runs[name].recon.rasterizer_name != "cpu":
            pytest.skip("the native cpu rasterizer is not built: too few torch-rasterizer steps fit the test's budget")
        runs[name].train()
    return runs


def metrics(trainer):
    return [json.loads(line) for line in (trainer.run_dir / "metrics.jsonl").read_text().splitlines()]


def check_completed_schedule(trainer, budget, grew=True):
    """The run spent ``budget`` seconds plus at most one step and ran its whole schedule
    (``grew``: growth seen before the stop)."""
    records = metrics(trainer)
    steps = [r for r in records if "loss" in r]
    final = records[-1]
    assert final.get("final") and steps[-1]["step"] == trainer.step and len(steps) >= 4
    walls = [r["wall"] for r in steps]
    durations = [b - a for a, b in zip(walls, walls[1:])]  # of every step logged but the first
    assert walls[-1] >= budget and walls[-2] < budget  # stopped at the first step ending past the budget
    assert walls[-1] - budget < durations[-1]  # exceeded by less than one step
    schedule = final["eval"]["schedule"]
    S = schedule["schedule_steps"]
    assert schedule["clock"] == "time" and schedule["max_steps"] is None and S == DEFAULT_SCHEDULE_STEPS
    # the last step ran at the schedule step the step before it reached in its densify stage,
    # after the step before that had ended: the end of the schedule but for two steps' clock
    last_position = steps[-2]["schedule_step"]
    assert last_position >= math.floor(S * walls[-3] / budget)
    group = next(g for g in trainer.optimizers.groups["background"] if g.name == "means")
    assert group.lr_final is not None and group.warmup_steps == 0
    assert schedule["final_lr"]["background.means"] == pytest.approx(
        exponential_lr(group.lr, group.lr_final, last_position, S), rel=1e-12)
    decayed = math.log(group.lr / schedule["final_lr"]["background.means"]) / math.log(group.lr / group.lr_final)
    assert decayed >= walls[-3] / budget - 1 / S  # the lr decay is complete but for the last two steps' share
    # densification stopped growing at half of the schedule, i.e. at half the budget: the
    # step before ran growth decisions before it, the stop is seen within the next two steps
    stopped = schedule["densify_stopped"]
    assert schedule["densify_stop_schedule_step"] == S // 2
    by_step = {r["step"]: r for r in steps}
    k = stopped["step"]
    if k in by_step:  # (else stopped before the checkpoint a resumed run started from)
        assert stopped["schedule_step"] == by_step[k]["schedule_step"] >= S // 2
        assert k - 1 not in by_step or by_step[k - 1]["schedule_step"] < S // 2
        two_steps = by_step[k]["wall"] - by_step.get(k - 2, {"wall": 0.0})["wall"]
        assert budget / 2 <= stopped["train_seconds"] <= budget / 2 + two_steps
    before = [r["num_gaussians"] for r in steps if r["step"] < stopped["step"]]
    after = [r["num_gaussians"] for r in steps if r["step"] >= stopped["step"]]
    if grew:
        assert max(before) > before[0]  # it grew before (from schedule step 500 on, every 2 steps)
    assert after == sorted(after, reverse=True)  # and not after (pruning only)
    # the SH degree of the schedule's end, by every tool that loads the run
    recon = Reconstruction.from_run(trainer.run_dir, load_plugins())
    assert recon.schedule_step == trainer.recon.schedule_step > trainer.step
    assert recon.sh_degree() == min(3, trainer.recon.schedule_step // trainer.config.method.sh_degree_interval) >= 2
    return schedule


@pytest.mark.parametrize("name", ["fast", "slow"])
def test_a_time_budget_alone_completes_every_schedule(timed, name):
    schedule = check_completed_schedule(timed[name], BUDGET)
    assert json.loads((timed[name].run_dir / "run.json").read_text())["schedule"] == schedule  # run.json says it
    assert timed["slow"].step < timed["fast"].step  # the slow step: fewer steps, the same schedule


def test_a_time_budget_resumes_on_its_clock(synth, timed):
    checkpoint = timed["slow"].run_dir / "checkpoints" / "step-000008.pt"
    state = torch.load(checkpoint, weights_only=True)
    assert 0 < state["train_seconds"] < BUDGET and state["schedule_step"] > 8
    resumed = trainer_of(synth, "slow-resumed", ["--trainer.max-seconds", str(BUDGET), "--trainer.resume",
                                                 str(checkpoint)], SlowTrainer, TIMED_METHOD)
    assert (resumed.step, resumed.recon.schedule_step, resumed.train_seconds) == (
        8, state["schedule_step"], state["train_seconds"])
    assert resumed.densify_stop == state["densify_stop"]
    resumed.train()
    check_completed_schedule(resumed, BUDGET, grew=False)


def test_a_step_budget_continues_a_time_runs_schedule_step(synth, timed):
    """Continuing a time run on steps (as ``omnire compact`` fine-tunes) keeps its schedule
    step, one more per step, and saves it: the continued run renders at its SH degree."""
    slow = timed["slow"]
    end = slow.recon.schedule_step
    more = trainer_of(synth, "slow-more", ["--trainer.max-steps", str(slow.step + 2), "--trainer.resume",
                                           str(slow.run_dir)], method=TIMED_METHOD)
    assert (more.step, more.recon.schedule_step) == (slow.step, end)
    more.train()
    assert (more.step, more.recon.schedule_step) == (slow.step + 2, end + 2)
    recon = Reconstruction.from_run(more.run_dir, load_plugins())
    # the degree of the saved schedule step, not of the step count (some 25 steps: degree 0);
    # 2 or 3, as the time run ended short of the band at schedule step 3000 or not
    assert recon.schedule_step == end + 2 and recon.sh_degree() >= max(2, slow.recon.sh_degree())
