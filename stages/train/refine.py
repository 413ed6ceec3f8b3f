"""Pose refinement as a hook of train's loop (`train --refine-poses`, `model.camera_opt`): the training rays go
through each camera's correction, the corrections take their own step after the field's, and when the guard stops
refinement the model goes back to its state at the cameras' first move (`model.camera_opt` "Rollback").

The hook adds the corrections to checkpoint.pt (`camera_opt`), to the parameters data-parallel runs average, to the
state the ranks compare, and maps held-out rays into the refined frame (`eval_rays`).
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from nerfpipe.model.camera_opt import CameraOpt
from nerfpipe.model.methods import Hook, LoopState

__all__ = ["PoseRefinement"]


class PoseRefinement(Hook):
    """The training cameras' corrections, stepped with the model (module doc)."""

    name = "pose_refinement"

    def __init__(self, cameras: CameraOpt):
        self.cameras = cameras
        self._before: tuple[int, Any] | None = None  # (step, the loop's snapshot) when the cameras first moved
        self._rolled_back = False  # the model went back to _before: prepare() tells the loop once

    @property
    def refining(self) -> bool:
        """Whether rays go through the corrections: until the guard stops refinement (then the corrections are zero
        and the rays are the input cameras', as in a run without refinement)."""
        return self.cameras.log.stopped_at is None

    def prepare(self, loop: LoopState, fraction: float) -> bool:
        rolled_back, self._rolled_back = self._rolled_back, False
        return rolled_back  # the loop keeps a new good state for its non-finite recovery

    def rays(self, loop: LoopState, o: Tensor, d: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        return self.cameras(o, d, view) if self.refining else (o, d)

    def after_step(self, loop: LoopState) -> None:
        """The cameras' step after the model's; the model's state is kept at the cameras' first move, and restored
        when the guard stops refinement."""
        cams, frac, step = self.cameras, loop.fraction(), loop.step + 1
        if self._before is None and cams.moves(frac):  # the model has only seen the input cameras so far
            self._before = (step, loop.snapshot())
        cams.step(frac, step=step)  # the guard records the step it acts at
        if cams.log.stopped_at == step and self._before is not None:
            kept_at, state = self._before
            loop.restore(state)
            cams.log.rolled_back_to = kept_at
            self._rolled_back = True
            self._before = None

    def eval_rays(self) -> Any:
        return self.cameras.test_rays()

    def parameters(self) -> list[Tensor]:
        return [p for p in self.cameras.parameters() if p.requires_grad]

    def fingerprint(self) -> dict[str, Tensor]:
        return {"cameras": self.cameras.raw}

    def checkpoint(self) -> dict[str, Any]:
        return {"camera_opt": self.cameras.to_dict()}
