"""Hooks: the pieces of a training run that a method or an option plugs into the one loop (gsplat's `Strategy`).

The loop (`stages.train.loop.Loop`) holds only what every run has: the model, its optimiser, the photos, the clock,
the budget, the schedule, checkpoints, interrupts and data-parallel averaging. Everything else is a `Hook`: the
density field's grid upsampling, occupancy refresh and priors (`model.methods.density.hooks`), pose refinement
(`stages.train.refine`). Each call gets the loop's public state (`LoopState`). A hook overrides what it needs;
every other call does nothing.

Order within a step (the loop calls every hook in list order at each point):
  prepare(fraction) -> draw(n) (the first hook that returns a batch draws it) -> rays(o, d, view) -> render ->
  loss(batch, out) -> backward -> after_backward ->
  optimiser step -> model.after_step -> after_step
and finish() once the budget is spent, before the last checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import torch
from torch import Tensor

__all__ = ["Hook", "LoopState", "Batch"]


class LoopState(Protocol):
    """What a hook may read or change of the loop."""

    model: Any
    """The method's `TrainModel`."""
    opt: torch.optim.Optimizer
    step: int
    gen: torch.Generator
    """The run's generator (batches, background colours, priors' random texels)."""
    device: torch.device
    config: Any
    """train's resolved Config."""

    def fraction(self) -> float:
        """Progress through the run now (the loop's budget)."""
        ...

    def transform_rays(self, o: Tensor, d: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        """Rays o, d [R, 3] of training views view [R] as a step renders them (every hook's `rays`, in order)."""
        ...

    def rebuild_optimizer(self, state: dict | None = None) -> None:
        """A new optimiser over the model's parameters now (after their shapes changed), with `state` if given."""
        ...

    def snapshot(self) -> Any:
        """The model's learned state and the optimiser's, copied."""
        ...

    def restore(self, snapshot: Any) -> None:
        """Back to `snapshot` (model and optimiser; a new optimiser when the shapes changed since)."""
        ...


@dataclass(frozen=True)
class Batch:
    """A training step's rays as the loss hooks see them."""

    o: Tensor  # [R, 3] this rank's rays (after `Hook.rays`)
    d: Tensor  # [R, 3] unit
    view: Tensor  # [R] each ray's training view
    background: Tensor  # [R, 3] or [3]: this rank's background colours
    background_all: Tensor  # the whole batch's (data-parallel: every rank's)
    share: float
    """Weight of this rank's per-ray terms (n_r W / B; 1 in one process)."""


class Hook:
    """A piece of training plugged into the loop (module doc). Every method here does nothing by default."""

    name: str = "hook"

    def prepare(self, loop: LoopState, fraction: float) -> bool:
        """Before a step at run progress `fraction`; True when the model or the optimiser was replaced (the loop
        keeps a new good state for its recovery)."""
        return False

    def draw(self, loop: LoopState, n: int) -> Tensor | None:
        """The step's n rays as flat indices [n] into the training photos' pixels (`model.views.Views`), drawn with
        loop.gen; None: another hook's, or the loop's own (uniform over every pixel of every photo)."""
        return None

    def rays(self, loop: LoopState, o: Tensor, d: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        """The batch's rays o, d [R, 3] of training views view [R] as the step renders them."""
        return o, d

    def loss(self, loop: LoopState, batch: Batch, out: dict[str, Tensor]) -> Tensor | None:
        """A term added to the step's loss (None: nothing)."""
        return None

    def after_backward(self, loop: LoopState) -> None:
        """After the gradients are in (and averaged across ranks), before the optimiser steps."""

    def after_step(self, loop: LoopState) -> None:
        """After the optimiser's step and the model's own `after_step`."""

    def finish(self, loop: LoopState) -> None:
        """The budget is spent: final touches before the last checkpoint."""

    def eval_rays(self) -> Any:
        """A map (o, d) -> (o, d) of held-out rays into the frame the model is trained in now (pose refinement's
        refined frame); None: the held-out rays are used as given."""
        return None

    def parameters(self) -> list[Tensor]:
        """Parameters outside the optimiser that the step's backward reaches (averaged across ranks)."""
        return []

    def fingerprint(self) -> dict[str, Tensor]:
        """Named state that must be the same on every rank (compared at the start and at each checkpoint)."""
        return {}

    def checkpoint(self) -> dict[str, Any]:
        """Entries this hook adds to checkpoint.pt."""
        return {}

    def metrics(self) -> dict[str, str]:
        """Columns this hook fills in the step's metrics row."""
        return {}
