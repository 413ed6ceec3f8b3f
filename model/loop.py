"""The one training loop: clock, budget, progress, learning-rate schedule, checkpoint cadence, interrupts, resume
and recovery from non-finite losses. `train`, `xray-train` and `fit-image` each supply their step (`Stepper`).

    clock = Clock(seconds_before)                       # training seconds, across resumes
    loop = TrainingLoop(settings, stepper, clock, stop)  # stop: data.stop.StopRequest, or None
    seconds = loop.run()

Progress through a run is the larger of the step and the clock fractions (`Budget.fraction`), so a time budget gets
the whole schedule: the learning rate decays exponentially from `lr` to `lr * lr_decay` over the run, times the
run's `lr_factor` (halved by each recovery; `Schedule.lr`). The clock counts training seconds only: what runs inside
`clock.paused()` (periodic evaluation) is left out of the budget, the schedule and the logged seconds.

Checkpoints (`Stepper.checkpoint`): every `checkpoint_every` steps, every `checkpoint_seconds` of wall-clock time
(so a killed run loses at most that), at the end (`Stepper.finish`), and when `stop` (`data.stop`: SIGINT/SIGTERM)
is raised: the loop then saves the current step and raises `data.errors.Interrupted` ("interrupted (SIGINT) at step
N after S s; continue with --resume"). Resuming is the mode's own: it reads its checkpoint back (step, seconds,
lr_factor, random state, model and optimiser) into the stepper and the clock, then runs a loop with them.

A step whose loss is not finite changes nothing and returns False; the loop then restores the last good state
(`Stepper.snapshot`, kept every `keep_every` steps and whenever `Stepper.prepare` changed the model), goes back to
its step, halves the learning rate and goes on; the third time it raises TrainingDiverged.

Data-parallel runs (`model.distributed`, torchrun): every rank runs this loop, and the decisions that read a
clock or a signal must fall on the same step everywhere. `agree` (`DataParallel.agree`), called once a step and once
more around the end, gives every rank any rank's stop signal, rank 0's training seconds (the budget, the schedule and
the interrupt message read them) and rank 0's wall-clock checkpoint decision (taken at the top of the step, acted
on at its end). Without `agree` (one process) the loop reads its own clock and signal, as it always has.

Why in model/: the loop drives models and their optimisers and decides when checkpoints are written (their format
is model.checkpoint's, model.xray's); data/ holds file formats and radiance/ the maths, and stages never import one
another, so the loop the three stages share lives here, below them.
"""

from __future__ import annotations

import contextlib
import copy
import signal
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch

from nerfpipe.data.errors import Interrupted
from nerfpipe.data.stop import StopRequest

__all__ = [
    "Budget",
    "Clock",
    "Schedule",
    "LoopSettings",
    "Stepper",
    "NetStepper",
    "TrainingLoop",
    "TrainingDiverged",
    "set_lr",
    "Agreement",
]

Agreement = Callable[[int | None, float, bool], tuple[int | None, float, bool]]
"""(this rank's stop signal, training seconds, wall-clock checkpoint due) -> what every rank takes: any rank's
signal, rank 0's seconds, rank 0's decision (`model.distributed.DataParallel.agree`)."""


class TrainingDiverged(RuntimeError):
    """The loss went non-finite repeatedly, even after restoring the last good state with a lower LR."""


def set_lr(opt: torch.optim.Optimizer, lr: float) -> None:
    """Every parameter group at lr times its `lr_scale` (1 when it has none)."""
    for g in opt.param_groups:
        g["lr"] = lr * g.get("lr_scale", 1.0)


@dataclass(frozen=True, kw_only=True)
class Budget:
    """When a run ends: after max_steps optimiser steps or max_seconds training seconds, whichever comes first."""

    max_steps: int
    max_seconds: float

    def fraction(self, step: int, seconds: float) -> float:
        """Progress through the run: the larger of the step and the time fractions (>= 1: spent)."""
        return max(step / max(self.max_steps, 1), seconds / self.max_seconds)


@dataclass(frozen=True, kw_only=True)
class Schedule:
    """Exponential learning-rate decay from lr (progress 0) to lr * decay (progress 1)."""

    lr: float
    decay: float = 1.0

    def at(self, fraction: float, factor: float = 1.0) -> float:
        """The learning rate at run progress `fraction`, times the run's recovery factor."""
        return self.lr * factor * self.decay**fraction


class Clock:
    """Training seconds: `before` (earlier runs of a resumed one) plus wall-clock time since `start()`, less the
    time spent inside `paused()` blocks."""

    def __init__(self, before: float = 0.0) -> None:
        self.before = before
        self._t0: float | None = None
        self._paused = 0.0

    def start(self) -> None:
        self._t0, self._paused = time.perf_counter(), 0.0

    def __call__(self) -> float:
        if self._t0 is None:
            return self.before
        return self.before + time.perf_counter() - self._t0 - self._paused

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Time inside the block is not training time (evaluation)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._paused += time.perf_counter() - t0


@dataclass(frozen=True, kw_only=True)
class LoopSettings:
    name: str
    """The mode, in messages ("train: non-finite loss; ...")."""
    budget: Budget
    schedule: Schedule
    checkpoint_every: int = 0
    """Checkpoint every this many steps (0: off)."""
    checkpoint_seconds: float = 0.0
    """Checkpoint every this many wall-clock seconds (0: off)."""
    checkpoint_path: Path | None = None
    """Named in the interrupt and divergence messages (None: the mode keeps no checkpoint)."""
    keep_every: int = 100
    """Keep a good state (for non-finite recovery) every this many steps."""
    max_failures: int = 3
    """Non-finite losses the run survives, less one (each restores the last good state at half the rate)."""


class Stepper(Protocol):
    """What a mode supplies to the loop: its state, its step and its records."""

    step: int
    """Optimiser steps taken (counted across resumes); the loop advances it and puts it back on recovery."""
    lr_factor: float
    """Learning-rate factor (saved across resumes); the loop halves it on recovery."""
    opt: torch.optim.Optimizer
    """The loop sets its learning rate (`set_lr`) before every step."""

    def prepare(self, fraction: float) -> bool:
        """Schedule changes before a step at run progress `fraction` (upsampling, grid refresh); True when the
        model or the optimiser was replaced (the loop keeps a new good state)."""
        ...

    def train_step(self, lr: float) -> bool:
        """One optimiser step at `lr`; False, and nothing changed, when the loss is not finite."""
        ...

    def log(self, lr: float) -> None:
        """After each good step: metrics rows, evaluation (inside `clock.paused()`), the progress display."""
        ...

    def snapshot(self) -> Any:
        """A copy of what a recovery restores (model and optimiser state; the loop keeps the step)."""
        ...

    def restore(self, snapshot: Any) -> None: ...

    def checkpoint(self, seconds: float) -> None:
        """Save the run at the current step (periodic, and on an interrupt) with `seconds` of training."""
        ...

    def finish(self, seconds: float) -> None:
        """The budget is spent: final touches and the last checkpoint."""
        ...


@dataclass(eq=False, kw_only=True)
class NetStepper:
    """The bookkeeping of a `Stepper` that trains one network with one optimiser and saves through a callback
    (the pretraining stages): no schedule changes, snapshots of both state dicts, checkpoints by `on_checkpoint`.
    A subclass adds its data and supplies `train_step` and `log`."""

    net: torch.nn.Module
    opt: torch.optim.Optimizer
    on_checkpoint: Callable[[float], None]
    """(training seconds) -> None: write the partial weights."""
    step: int = 0
    lr_factor: float = 1.0

    def prepare(self, fraction: float) -> bool:
        return False

    def snapshot(self) -> tuple[dict, dict]:
        return copy.deepcopy(self.net.state_dict()), copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[dict, dict]) -> None:
        self.net.load_state_dict(snapshot[0])
        self.opt.load_state_dict(snapshot[1])

    def checkpoint(self, seconds: float) -> None:
        self.on_checkpoint(seconds)

    def finish(self, seconds: float) -> None:
        pass


class TrainingLoop:
    """Steps `stepper` until the budget is spent (see the module doc); `stop` is polled between steps; `agree`
    (data-parallel runs) makes every rank take the same decisions."""

    def __init__(
        self,
        settings: LoopSettings,
        stepper: Stepper,
        clock: Clock,
        stop: StopRequest | None = None,
        agree: Agreement | None = None,
    ):
        self.settings, self.stepper, self.clock, self.stop = settings, stepper, clock, stop
        self.agree = agree
        self._agreed: tuple[int | None, float, bool] = (None, clock.before, False)
        self._checkpoint_wall = 0.0  # time.perf_counter() at the last checkpoint
        self.failures = 0

    def fraction(self) -> float:
        """Progress through the run now (data-parallel: as of this step's agreement)."""
        return self.settings.budget.fraction(self.stepper.step, self._now())

    def run(self) -> float:
        """Train until the budget is spent; returns the training seconds (across resumes)."""
        settings, stepper = self.settings, self.stepper
        self.clock.start()
        self._checkpoint_wall = time.perf_counter()
        good = self._keep()
        while stepper.step < settings.budget.max_steps:
            self._tick()
            self._poll()
            fraction = self.fraction()
            if fraction >= 1.0:
                break
            if stepper.prepare(fraction):
                good = self._keep()
            lr = settings.schedule.at(fraction, stepper.lr_factor)
            set_lr(stepper.opt, lr)
            if not stepper.train_step(lr):
                self._recover(good)
                continue
            stepper.step += 1
            if stepper.step % settings.keep_every == 0:
                good = self._keep()
            stepper.log(lr)
            if self._checkpoint_due():
                self._checkpoint(self._now())
        self._tick()
        seconds = self._now()
        stepper.finish(seconds)
        self._tick()
        if self._signum() is not None:  # the signal came during the last checkpoint
            self._interrupted(seconds)
        return seconds

    def _tick(self) -> None:
        """Data-parallel: this step's agreement (module doc); alone: nothing."""
        if self.agree is not None:
            signum = self.stop.signum if self.stop is not None else None
            every_s = self.settings.checkpoint_seconds
            wall_due = every_s > 0 and time.perf_counter() - self._checkpoint_wall >= every_s
            self._agreed = self.agree(signum, self.clock(), wall_due)

    def _now(self) -> float:
        """Training seconds: the clock's, or (data-parallel) rank 0's as of the last agreement."""
        return self.clock() if self.agree is None else self._agreed[1]

    def _signum(self) -> int | None:
        if self.agree is not None:
            return self._agreed[0]
        return self.stop.signum if self.stop is not None else None

    def _poll(self) -> None:
        if self._signum() is not None:
            seconds = self._now()
            self._checkpoint(seconds)
            self._interrupted(seconds)

    def _interrupted(self, seconds: float) -> None:
        signum = self._signum()
        where = f" (checkpoint {self.settings.checkpoint_path})" if self.settings.checkpoint_path else ""
        raise Interrupted(
            f"interrupted ({signal.Signals(signum).name}) at step {self.stepper.step} after "
            f"{seconds:.1f} s; continue with --resume{where}",
            signum,
        )

    def _checkpoint_due(self) -> bool:
        every, every_s = self.settings.checkpoint_every, self.settings.checkpoint_seconds
        if every > 0 and self.stepper.step % every == 0:
            return True
        if self.agree is not None:
            return self._agreed[2]
        return every_s > 0 and time.perf_counter() - self._checkpoint_wall >= every_s

    def _checkpoint(self, seconds: float) -> None:
        self.stepper.checkpoint(seconds)
        self._checkpoint_wall = time.perf_counter()
        self._agreed = (*self._agreed[:2], False)  # the agreed wall-clock checkpoint is taken

    def _keep(self) -> tuple[Any, int]:
        return self.stepper.snapshot(), self.stepper.step

    def _recover(self, good: tuple[Any, int]) -> None:
        """Back to the last good state at half the learning rate; TrainingDiverged after max_failures."""
        self.failures += 1
        settings, stepper = self.settings, self.stepper
        if self.failures >= settings.max_failures:
            path = settings.checkpoint_path
            if path is None:
                kept = f" ({settings.name}; try a lower --lr)"
            else:
                kept = f"; last checkpoint kept in {path}" if path.exists() else f"; no checkpoint written to {path}"
            raise TrainingDiverged(
                f"loss is not finite at step {stepper.step} after {self.failures} restores with "
                f"lower learning rates{kept}"
            )
        snapshot, stepper.step = good
        stepper.restore(snapshot)
        stepper.lr_factor *= 0.5
        print(
            f"{settings.name}: non-finite loss; restored step {stepper.step}, learning rate x{stepper.lr_factor}",
            file=sys.stderr,
        )
