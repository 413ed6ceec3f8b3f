"""The density method's pieces of training (`model.methods.hooks.Hook`): coarse-to-fine upsampling, the occupancy
grid's refresh, and the priors (L1 on density, mip-NeRF 360's distortion, DS-NeRF's depth loss, TensoRF's TV).

Each is on only where its option asks for it (`hooks_for`); a step calls them in the order of that list: the loss
terms L1, distortion, depth; after the backward pass the TV gradient (added after the ranks' gradients are
averaged: its texels are drawn from the run's generator, identically on every rank).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from nerfpipe.model.field_model import MarchedModel
from nerfpipe.model.methods.density.options import DensityOptions
from nerfpipe.model.methods.hooks import Batch, Hook, LoopState
from nerfpipe.model.views import DepthRays
from nerfpipe.radiance.fields import TensoRF
from nerfpipe.radiance.regularizers import depth_nll_loss

__all__ = [
    "DEPTH_RAYS",
    "DEPTH_SIGMA",
    "TV_TEXELS",
    "upsample_schedule",
    "Upsampling",
    "OccupancyRefresh",
    "DensityL1",
    "Distortion",
    "DepthLoss",
    "TotalVariation",
    "hooks_for",
]

DEPTH_RAYS = 256
"""Sparse-point rays rendered per step for the depth loss (a quarter of the CPU photometric batch)."""
DEPTH_SIGMA = 0.02
"""Depth uncertainty of a structure-from-motion point, as a fraction of its distance (DS-NeRF's sigma)."""
TV_TEXELS = 4096
"""Random texels per plane in each step's total-variation estimate (`TensoRF.tv`)."""
OCCUPANCY_WARMUP = 64
"""Steps during which every occupancy cell is refreshed (the field is still a fog)."""


def upsample_schedule(resolution: tuple[int, int], upsample_at: tuple[float, ...]) -> list[tuple[float, int]]:
    """(progress fraction, grid resolution) pairs: geometric steps from resolution[0] to resolution[1]."""
    r0, r1 = resolution
    n = len(upsample_at)
    if n == 0 or r0 == r1:
        return []
    res = [round(math.exp(math.log(r0) + (math.log(r1) - math.log(r0)) * (k + 1) / n)) for k in range(n)]
    return list(zip(upsample_at, res, strict=True))


class Upsampling(Hook):
    """Coarse-to-fine: the grid is resampled at the schedule's run fractions (new parameters: a new optimiser)."""

    name = "upsampling"

    def __init__(self, resolution: tuple[int, int], upsample_at: tuple[float, ...]):
        self.schedule = upsample_schedule(resolution, upsample_at)

    def prepare(self, loop: LoopState, fraction: float) -> bool:
        field, upsampled = loop.model.field, False
        while self.schedule and fraction >= self.schedule[0][0]:
            _, res = self.schedule.pop(0)
            if res > field.resolution:
                field.upsample(res)
                loop.rebuild_optimizer()
                upsampled = True
        return upsampled


class OccupancyRefresh(Hook):
    """The occupancy grid follows the field: part of its cells every `every` steps, every cell at the end (render
    and mesh skip by the saved grid, which must match the final field)."""

    name = "occupancy"

    def __init__(self, every: int, model: MarchedModel):
        self.every, self.model = every, model

    def prepare(self, loop: LoopState, fraction: float) -> bool:
        model = loop.model
        model.grid.update(model.field.density, loop.step, every=self.every, warmup_steps=OCCUPANCY_WARMUP)
        return False

    def finish(self, loop: LoopState) -> None:
        model = loop.model
        model.grid.update(model.field.density, loop.step, full=True, points_per_cell=4)

    def metrics(self) -> dict[str, str]:
        return {"skip_fraction": f"{self.model.grid.skip_fraction:.4f}"}


class DensityL1(Hook):
    """L1 sparsity prior on the density factors (counted alike on every rank)."""

    name = "density_l1"

    def __init__(self, weight: float):
        self.weight = weight

    def loss(self, loop: LoopState, batch: Batch, out: dict[str, Tensor]) -> Tensor:
        return self.weight * loop.model.field.density_l1()


class Distortion(Hook):
    """mip-NeRF 360's distortion loss on the step's rays (a per-ray term: weighted by the rank's share)."""

    name = "distortion"

    def __init__(self, weight: float):
        self.weight = weight

    def loss(self, loop: LoopState, batch: Batch, out: dict[str, Tensor]) -> Tensor:
        return batch.share * self.weight * loop.model.distortion(out, batch.o, batch.d)


class DepthLoss(Hook):
    """DS-NeRF's loss on DEPTH_RAYS random rays through the training cameras' sparse points, rendered each step."""

    name = "depth_loss"

    def __init__(self, weight: float, rays: DepthRays):
        self.weight, self.depth_rays = weight, rays

    def loss(self, loop: LoopState, batch: Batch, out: dict[str, Tensor]) -> Tensor:
        rays = self.depth_rays
        k = torch.randint(rays.depth.shape[0], (DEPTH_RAYS,), generator=loop.gen)
        o, d, depth, view = (t[k].to(loop.device) for t in (rays.o, rays.d, rays.depth, rays.view))
        o, d = loop.transform_rays(o, d, view)
        bg = batch.background_all
        if bg.ndim == 2:  # per-ray colours of the photometric batch, reused (the colour does not enter the loss)
            bg = bg[torch.arange(o.shape[0], device=bg.device) % bg.shape[0]]
        render = loop.model.render(o, d, bg.detach(), train=True, gen=None, view=view)
        term = depth_nll_loss(
            render["weights"], render["t_starts"], render["t_ends"], render["ray_indices"], depth, DEPTH_SIGMA * depth
        )
        return self.weight * term


class TotalVariation(Hook):
    """TensoRF's TV prior on the planes: its gradient on TV_TEXELS random texels per plane, after backward. `field`
    picks the TensoRF from the model (None: the model's `field`; the sdf method's: its outside field)."""

    name = "tv"

    def __init__(self, weight: float, field: Callable[[Any], TensoRF] | None = None):
        self.weight = weight
        self.field = field

    def after_backward(self, loop: LoopState) -> None:
        field = loop.model.field if self.field is None else self.field(loop.model)
        field.add_tv_grad_(self.weight, TV_TEXELS, loop.gen)


def hooks_for(options: DensityOptions, model: MarchedModel, depth_rays: DepthRays | None) -> list[Hook]:
    """The hooks `options` (resolved) switch on, in call order."""
    hooks: list[Hook] = [Upsampling(options.resolution, options.upsample_at)]
    if model.grid is not None:
        hooks.append(OccupancyRefresh(options.occupancy_every, model))
    if options.density_l1 > 0:
        hooks.append(DensityL1(options.density_l1))
    if options.distortion:
        hooks.append(Distortion(options.distortion))
    if depth_rays is not None and options.depth_loss:
        hooks.append(DepthLoss(options.depth_loss, depth_rays))
    if options.tv > 0:
        hooks.append(TotalVariation(options.tv))
    return hooks
