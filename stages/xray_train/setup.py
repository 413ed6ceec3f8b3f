"""`xray-train`'s start: the reference attenuation, the coarse-to-fine schedule, the learning rate, and the field
and optimiser, new or read back from RUN_DIR/checkpoint.pt (`--resume`: step, training seconds, learning-rate
factor, schedule level and the random state continue where the checkpoint left them)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.projections import ProjectionScene
from nerfpipe.model.xray import (
    XRAY_FIELDS,
    attenuation_field,
    build_field,
    grid_shape_at,
    read_xray_checkpoint,
    samples_for,
)
from nerfpipe.radiance.aabb import ray_aabb_intersect
from nerfpipe.radiance.fields import Field
from nerfpipe.radiance.xray import rays_for_pixels

__all__ = ["DEFAULT_LR", "Start", "make_optimizer", "mu_ref", "resolution_schedule", "samples_per_level", "start"]

DEFAULT_LR = {("adam", "grid"): 0.02, ("adam", "tensorf"): 0.02, ("sart", "grid"): 0.5}


@dataclass(kw_only=True)
class Start:
    """Where a run starts: a new field at step 0, or a checkpoint's."""

    model: Field
    opt: torch.optim.Optimizer
    mu_ref: float
    lr: float
    """The base learning rate (Config.lr or DEFAULT_LR)."""
    schedule: list[int]
    """Voxels along the longest axis at each level of the coarse-to-fine schedule."""
    step: int = 0
    seconds: float = 0.0
    lr_factor: float = 1.0
    level: int = 0


def make_optimizer(model: Field, lr: float) -> torch.optim.Adam:
    return torch.optim.Adam(model.param_groups(lr), betas=(0.9, 0.99))


def mu_ref(scene: ProjectionScene, gen: torch.Generator, n: int = 65536) -> float:
    """Twice the mean attenuation the training rays see: sum p / sum chord over a random subset."""
    train = torch.as_tensor(scene.split("train"))
    proj = torch.from_numpy(scene.projections).reshape(scene.geometry.n_views, -1)
    views = train[torch.randint(0, train.numel(), (n,), generator=gen)]
    pixels = torch.randint(0, proj.shape[1], (n,), generator=gen)
    o, d = rays_for_pixels(scene.geometry, views, pixels, dtype=torch.float64)
    t0, t1, hit = ray_aabb_intersect(o, d, torch.as_tensor(scene.grid.box))
    chord = float((t1 - t0)[hit].sum())
    total = float(proj[views, pixels][hit].clamp(min=0).sum())
    mean = total / chord if chord > 0 else 0.0
    return 2 * mean if mean > 0 else 1.0 / float(np.linalg.norm(np.asarray(scene.grid.shape) * scene.grid.spacing))


def resolution_schedule(config: Any, grid_longest: int) -> list[int]:
    """Voxels along the longest axis at each level: geometric steps from resolution[0] to resolution[1]."""
    start, end = config.resolution or (max(2, grid_longest // 4), grid_longest)
    k = len(config.upsample_at)
    return [round(math.exp(math.log(start) + (math.log(end) - math.log(start)) * i / k)) for i in range(k + 1)]


def samples_per_level(scene: ProjectionScene, step_ratio: float, schedule: list[int]) -> list[int]:
    """Samples per ray at each level: the step follows the level's voxel size (coarse grids: fewer samples)."""
    grid = scene.grid
    out = []
    for res in schedule:
        coarse = grid.shape[0] * grid.spacing[0] / grid_shape_at(grid, res)[0]
        out.append(samples_for(grid, step_ratio * coarse / grid.spacing[0]))
    return out


def start(config: Any, scene: ProjectionScene, device: torch.device, gen: torch.Generator) -> Start:
    """A new field (drawing mu_ref from `gen`), or with config.resume the checkpoint's (and `gen` set to its state)."""
    schedule = resolution_schedule(config, max(scene.grid.shape))
    lr = config.lr if config.lr is not None else DEFAULT_LR[config.optimizer, config.field]
    if config.resume:
        return _resumed(Path(config.run_dir) / "checkpoint.pt", config.field, device, gen, lr, schedule)
    ref = mu_ref(scene, gen)
    model = attenuation_field(scene.grid, kind=config.field, resolution=schedule[0], rank=config.rank, mu_ref=ref)
    model = model.to(device)
    return Start(model=model, opt=make_optimizer(model, lr), mu_ref=ref, lr=lr, schedule=schedule)


def _resumed(
    path: Path, field: str, device: torch.device, gen: torch.Generator, lr: float, schedule: list[int]
) -> Start:
    state = read_xray_checkpoint(path, device)
    if "rng" not in state:
        raise UserError(
            f"{path}: written by an xray-train without --resume (no step state to continue from); "
            "train again with --overwrite"
        )
    kind = state["field_config"].get("kind")
    if kind != XRAY_FIELDS[field].recorded_as:
        raise UserError(
            f"{path}: checkpoint holds a {kind!r} field, config asks for {field} ({XRAY_FIELDS[field].recorded_as!r})"
        )
    model = build_field(state["field_config"]).to(device)
    model.load_state_dict(state["field"])
    opt = make_optimizer(model, lr)
    opt.load_state_dict(state["optimizer"])
    gen.set_state(state["rng"].cpu())
    return Start(
        model=model,
        opt=opt,
        mu_ref=float(state["mu_ref"]),
        lr=lr,
        schedule=schedule,
        step=int(state["step"]),
        seconds=float(state["seconds"]),
        lr_factor=float(state["lr_factor"]),
        level=int(state["level"]),
    )
