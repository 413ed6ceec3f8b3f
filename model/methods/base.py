"""The method interface: what `train --method NAME` fits, and how its run is opened for the stages downstream.

A method is one module behind `Method`, found by name in the registry (`model.methods.registry`; nerfstudio's
`Model` and `method_configs` are the model of it). It owns:
- its options group (`Method.Options`: a frozen kw_only dataclass; a field whose default is None is an automatic
  default the method resolves from the scene and the device). `train` spells every method's options flat on its
  command line (`--resolution`, `--tv`, ...) and builds the chosen method's group from them;
- its defaults and rules (`prepare`: the options with every None resolved, each with its reason for the manifest's
  `used.defaults`, and the scene space its model lives in, if it uses one);
- its model (`build`: new, or from a checkpoint's entries), the pieces of training it plugs into the loop
  (`hooks`: `model.methods.hooks.Hook`), its learning rate, its entries in checkpoint.pt (`checkpoint`);
- what its runs can do for the stages downstream (`load` -> a `model.run.Run` that declares its capabilities).

`train` does everything every method shares: the scene, the photos as rays (`model.views`), the background, the
loop (clock, budget, schedule, checkpoints, interrupts, resume, data-parallel), pose refinement and appearance
codes (hooks of its own), the final evaluation, the reports and the manifest.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import torch
from torch import Tensor

from nerfpipe.data.transforms import Scene
from nerfpipe.model.background import Background
from nerfpipe.model.views import Views
from nerfpipe.radiance.space import Space

__all__ = ["Method", "TrainContext", "Prepared", "TrainModel", "RunFiles"]


@dataclass(frozen=True, kw_only=True)
class TrainContext:
    """What `train` has read and decided before a method resolves its options: the scene, its photos, the device,
    the background and the scene space its rule chose (`model.field_model.choose_space`)."""

    scene: Scene
    train: Views
    test: Views | None
    train_idx: tuple[int, ...]
    device: torch.device
    downscale: float
    background: Background
    space_kind: type[Space]
    """The scene model's choice for this scene (`train --scene-model`); a method may keep another (`prepare`)."""
    space_why: str
    refine_poses: bool
    """Pose refinement is on (a method's rules may go coarse-to-fine for it)."""

    @property
    def cuda(self) -> bool:
        return self.device.type == "cuda"


@dataclass(frozen=True, kw_only=True)
class Prepared:
    """A method's resolved options and the scene space its model lives in (None: the method uses none). A method
    may subclass it to carry what its build and hooks need (the density field's depth-loss rays)."""

    options: Any
    space: Space | None


class TrainModel(Protocol):
    """What `train` optimises and renders: rays in the scene frame (unit directions, t = Euclidean distance) to
    dict(rgb [R, 3], acc [R], depth [R], ...; while training also `samples`: the samples evaluated, a 0-d tensor)."""

    background: Background
    appearance: Any
    """Per-image appearance codes (`model.appearance.Appearance`), or None; `train --appearance` sets them."""
    space: Space | None
    chunk: int
    """Rays per evaluation chunk."""
    random_draws_per_ray: int
    """Random numbers a training render draws per ray from torch's generator (data-parallel runs place them)."""

    def render(
        self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, view: Tensor | None = None, **kw: Any
    ) -> dict[str, Tensor]: ...

    def param_groups(self, lr: float) -> list[dict]:
        """Adam's parameter groups at `lr` (each may carry an `lr_scale`)."""
        ...

    def train_mode(self, on: bool) -> None: ...

    def after_step(self) -> None:
        """After each optimiser step (caches that read the parameters must know they changed)."""
        ...

    def learned(self) -> dict[str, torch.nn.Module]:
        """What the model learned, by name (data-parallel runs compare them across ranks)."""
        ...

    def snapshot(self) -> Any:
        """A copy of everything learned (the loop's recovery and pose refinement's rollback restore it)."""
        ...

    def restore(self, snapshot: Any) -> bool:
        """Back to `snapshot`; True when the parameters' shapes changed since (the optimiser must start afresh)."""
        ...

    def describe(self) -> dict[str, Any]:
        """What the manifest's `used` says of the model (its configuration, its march, ...)."""
        ...


@dataclass(frozen=True)
class RunFiles:
    """A run folder as `load` gets it: the folder, its config.json (read) and where that was read."""

    run_dir: Path
    config: dict
    config_path: Path

    @property
    def checkpoint(self) -> Path:
        return self.run_dir / "checkpoint.pt"

    @property
    def downscale(self) -> float:
        """The image downscale the run trained at (1 for runs that did not record it)."""
        return float(self.config.get("downscale") or 1.0)


class Method(ABC):
    """One kind of model behind one interface (module doc). Subclasses set `name`, `summary` and `Options`."""

    name: ClassVar[str]
    """`train --method NAME`; config.json's `method`."""
    summary: ClassVar[str]
    """One line for `--help` and the README's table (tests/test_methods.py checks the table lists it)."""
    Options: ClassVar[type]
    """The method's options group (frozen kw_only dataclass, a docstring per field)."""
    recorded_before: ClassVar[Mapping[str, Any]] = {}
    """Automatic options a run recorded before the option existed had (resume reads them for older runs)."""

    def validate(self, options: Any) -> None:  # noqa: B027 - optional: most methods check nothing more
        """Every check the options alone allow (UserError naming the option), before any file is read."""

    def options_from(self, given: Mapping[str, Any]) -> Any:
        """The Options from a config.json's or the command line's values (unknown names are refused)."""
        known = {f.name for f in dataclasses.fields(self.Options)}
        extra = sorted(set(given) - known)
        if extra:
            raise ValueError(f"method {self.name} has no option {', '.join(extra)}")
        return self.Options(**given)

    @abstractmethod
    def prepare(self, ctx: TrainContext, options: Any, reasons: dict[str, str]) -> Prepared:
        """The options with every None resolved (each reason in `reasons`, and the scene model's in
        reasons["scene_model"]) and the space the model lives in."""

    @abstractmethod
    def default_lr(self) -> tuple[float, str]:
        """The base learning rate when none is given, and why."""

    def default_batch(self, cuda: bool) -> tuple[int, str] | None:
        """Rays a step when none is given, and why; None: train's rule for every method (1024 on CPU, 8192 on
        CUDA)."""
        return None

    @abstractmethod
    def build(self, ctx: TrainContext, prepared: Prepared, state: dict | None) -> TrainModel:
        """A new model (state None) or the one a checkpoint holds (its entries, `checkpoint`); the background is
        ctx.background (or the checkpoint's)."""

    def hooks(self, ctx: TrainContext, prepared: Prepared, model: TrainModel) -> list:
        """The pieces of training this method plugs into the loop (`model.methods.hooks.Hook`), in call order."""
        return []

    def checks(self, model: TrainModel) -> list:
        """The method's own self-checks of a finished model (`data.checks.Check`s the train manifest adds to its
        `checks`; an SDF's Eikonal residual and sharpness). None by default."""
        return []

    @abstractmethod
    def checkpoint(self, model: TrainModel) -> dict[str, Any]:
        """The method's entries in checkpoint.pt (tensors and primitive containers only)."""

    def optimizer_state(self, state: dict) -> dict:
        """The checkpoint's optimiser state as this version's parameter groups read it (older layouts mapped)."""
        return state["optimizer"]

    @abstractmethod
    def load(self, run: RunFiles, device: torch.device) -> Any:
        """The run, ready for the stages downstream (`model.run.Run`)."""
