"""The one training loop (`model.loop`) on a toy step: budget, progress, learning-rate schedule, paused clock,
checkpoint cadence, Ctrl-C (a stop request) with resume to the same end, and non-finite recovery."""

from __future__ import annotations

import copy
import signal
import time
from dataclasses import dataclass, field

import pytest
import torch

from nerfpipe.data.errors import Interrupted
from nerfpipe.data.stop import StopRequest
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingDiverged, TrainingLoop, set_lr


@dataclass
class Toy:
    """Fits w to 2 with Adam; records what the loop asked of it. `fail_at`: steps whose loss is "not finite"
    (once each); `stop_at`: the step after which a stop request (Ctrl-C) arrives."""

    step: int = 0
    lr_factor: float = 1.0
    w: torch.nn.Parameter = field(default_factory=lambda: torch.nn.Parameter(torch.zeros(1)))
    opt: torch.optim.Optimizer = None
    fail_at: set[int] = field(default_factory=set)
    stop_at: int | None = None
    stop: StopRequest | None = None
    step_seconds: float = 0.0
    eval_seconds: float = 0.0
    clock: Clock | None = None
    lrs: list[float] = field(default_factory=list)
    checkpoints: list[tuple[int, float]] = field(default_factory=list)
    finished: list[int] = field(default_factory=list)
    saved: dict | None = None

    def __post_init__(self) -> None:
        self.opt = torch.optim.Adam([self.w], lr=0.1)

    def prepare(self, fraction: float) -> bool:
        return False

    def train_step(self, lr: float) -> bool:
        if self.step in self.fail_at:
            self.fail_at.discard(self.step)
            return False
        self.lrs.append(lr)
        loss = ((self.w - 2.0) ** 2).sum()
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        time.sleep(self.step_seconds)
        if self.stop_at is not None and self.step + 1 == self.stop_at:
            self.stop.signum = signal.SIGINT
        return True

    def log(self, lr: float) -> None:
        if self.eval_seconds:
            with self.clock.paused():
                time.sleep(self.eval_seconds)

    def snapshot(self) -> tuple[dict, dict]:
        return {"w": self.w.detach().clone()}, copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[dict, dict]) -> None:
        with torch.no_grad():
            self.w.copy_(snapshot[0]["w"])
        self.opt.load_state_dict(snapshot[1])

    def checkpoint(self, seconds: float) -> None:
        self.checkpoints.append((self.step, seconds))
        self.saved = {"step": self.step, "seconds": seconds, "lr_factor": self.lr_factor, **self.snapshot()[1]}

    def finish(self, seconds: float) -> None:
        self.finished.append(self.step)


def _settings(max_steps: int = 10, max_seconds: float = float("inf"), **kw) -> LoopSettings:
    base = dict(
        name="toy", budget=Budget(max_steps=max_steps, max_seconds=max_seconds), schedule=Schedule(lr=0.1, decay=0.01)
    )
    base.update(kw)
    return LoopSettings(**base)


def _run(toy: Toy, settings: LoopSettings, before: float = 0.0, stop: StopRequest | None = None) -> float:
    toy.clock = Clock(before)
    return TrainingLoop(settings, toy, toy.clock, stop).run()


def test_step_budget_schedule_and_checkpoint_cadence():
    toy = Toy()
    _run(toy, _settings(max_steps=10, checkpoint_every=3))
    assert toy.step == 10 and toy.finished == [10]
    assert [s for s, _ in toy.checkpoints] == [3, 6, 9]
    # exponential decay from lr to lr * decay over the run's progress (here the step fraction)
    assert toy.lrs == pytest.approx([0.1 * 0.01 ** (k / 10) for k in range(10)], rel=1e-12)
    assert toy.opt.param_groups[0]["lr"] == pytest.approx(toy.lrs[-1])


def test_time_budget_and_paused_evaluation():
    toy = Toy(step_seconds=0.02, eval_seconds=0.05)
    t0 = time.perf_counter()
    seconds = _run(toy, _settings(max_steps=10_000, max_seconds=0.1))
    wall = time.perf_counter() - t0
    assert 0.1 <= seconds < wall - 0.05 * (toy.step - 1)  # evaluation left out of training seconds
    assert 2 <= toy.step < 10_000
    assert Budget(max_steps=100, max_seconds=10.0).fraction(25, 5.0) == 0.5  # the larger fraction


def test_stop_request_checkpoints_and_resume_reaches_the_same_end():
    straight = Toy()
    _run(straight, _settings())
    stop = StopRequest()
    toy = Toy(stop_at=4, stop=stop)
    with pytest.raises(Interrupted, match=r"interrupted \(SIGINT\) at step 4 after .* s; continue with --resume") as e:
        _run(toy, _settings(checkpoint_path="ckpt.pt"), stop=stop)
    assert e.value.exit_code == 130 and "(checkpoint ckpt.pt)" in str(e.value)
    assert [s for s, _ in toy.checkpoints] == [4] and toy.finished == []
    resumed = Toy(step=toy.saved["step"], lr_factor=toy.saved["lr_factor"])
    resumed.w.data.copy_(toy.w.data)
    resumed.opt.load_state_dict({k: toy.saved[k] for k in ("state", "param_groups")})
    seconds = _run(resumed, _settings(), before=toy.saved["seconds"])
    assert resumed.step == 10 and seconds >= toy.saved["seconds"]
    assert toy.lrs + resumed.lrs == straight.lrs and torch.equal(resumed.w, straight.w)


def test_stop_during_the_last_checkpoint_still_says_interrupted():
    stop = StopRequest()
    toy = Toy()
    toy.finish = lambda seconds: setattr(stop, "signum", signal.SIGTERM)  # the signal lands while finishing
    with pytest.raises(Interrupted, match=r"interrupted \(SIGTERM\) at step 10 ") as e:
        _run(toy, _settings(), stop=stop)
    assert e.value.exit_code == 143


def test_non_finite_loss_restores_the_last_good_state_at_half_the_rate(capsys):
    toy = Toy(fail_at={7})
    _run(toy, _settings(keep_every=5))
    assert toy.step == 10 and toy.lr_factor == 0.5
    assert "toy: non-finite loss; restored step 5, learning rate x0.5" in capsys.readouterr().err
    # steps 5 and 6 ran twice: the second time at half the rate
    assert toy.lrs[7] == pytest.approx(0.5 * 0.1 * 0.01 ** (5 / 10))
    toy = Toy(fail_at={2, 3, 4})
    with pytest.raises(TrainingDiverged, match=r"not finite at step 4 after 3 restores .* \(toy; try a lower --lr\)"):
        _run(toy, _settings())


def test_set_lr_keeps_each_groups_scale():
    a, b = torch.nn.Parameter(torch.zeros(1)), torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.Adam([{"params": [a], "lr": 1.0}, {"params": [b], "lr": 1.0, "lr_scale": 0.05}])
    set_lr(opt, 0.2)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([0.2, 0.01])


def test_agreement_decides_the_budget_the_stop_and_checkpoints_for_every_rank():
    """Data-parallel: each step's decisions come from `agree` (rank 0's seconds, any rank's signal, rank 0's
    wall-clock checkpoint), not from this rank's own clock or signal, so every rank ends at the same step."""
    calls: list[tuple[int, int | None, bool]] = []

    def rank0_seconds(toy: Toy, stop_at: int | None = None, wall_at: int | None = None):
        def agree(signum, seconds, wall_due):
            calls.append((toy.step, signum, wall_due))
            other = signal.SIGTERM if toy.step == stop_at else None  # another rank got the signal
            return other, float(toy.step), toy.step == wall_at  # rank 0's clock: one second a step

        return agree

    toy = Toy()
    toy.clock = Clock()
    seconds = TrainingLoop(
        _settings(max_steps=100, max_seconds=5.5, checkpoint_seconds=1e9),
        toy,
        toy.clock,
        agree=rank0_seconds(toy, wall_at=3),
    ).run()
    assert toy.step == 6 and seconds == 6.0 and toy.finished == [6]  # rank 0's 6 s spent the 5.5 s budget
    assert toy.lrs == pytest.approx([0.1 * 0.01 ** (k / 5.5) for k in range(6)], rel=1e-12)  # its fraction
    assert [s for s, _ in toy.checkpoints] == [4]  # due at the top of step 4 (step 3 done), taken at its end
    assert all(signum is None for _, signum, _ in calls)  # this rank got no signal of its own
    toy = Toy()
    toy.clock = Clock()
    with pytest.raises(Interrupted, match=r"interrupted \(SIGTERM\) at step 2 after 2.0 s") as e:
        TrainingLoop(
            _settings(checkpoint_path="ckpt.pt"), toy, toy.clock, StopRequest(), agree=rank0_seconds(toy, stop_at=2)
        ).run()
    assert e.value.exit_code == 143 and [s for s, _ in toy.checkpoints] == [2] and toy.finished == []
