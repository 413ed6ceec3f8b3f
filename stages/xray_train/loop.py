"""The optimisation loop of `xray-train`: random detector rays -> line integrals through the field -> MSE.

Per step: `batch_rays` (view, pixel) pairs drawn uniformly from the training views, their rays
(radiance.xray.rays_for_pixels), line integrals through the field (model.xray.field_line_integrals: stratified,
jittered samples over the ray's chord of the box, Beer-Lambert in the compositing core), loss
mean((p - p_measured)^2) + tv * TV(field) (grid field only). Adam; the learning rate decays exponentially to
`lr * lr_decay` over the run (progress = the larger of steps and seconds used); the grid field is projected
onto mu >= 0 after each step; coarse-to-fine upsampling at fixed fractions of the run.
Seconds count training only: evaluation pauses the clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from radiance.fields import Field
from radiance.xray import XrayGeometry, rays_for_pixels

__all__ = ["Batches", "LoopState", "make_optimizer", "train_step", "sart_step"]


@dataclass
class Batches:
    """Random (view, pixel) draws over the training views, and their measured line integrals."""

    geometry: XrayGeometry
    projections: Tensor  # [V, n_v * n_u] float32 (all views; only train_views are drawn)
    train_views: Tensor  # [T] long
    generator: torch.Generator

    def draw(self, n: int, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
        """(rays_o [n, 3], rays_d [n, 3], p [n]) on `device`."""
        npix = self.projections.shape[1]
        views = self.train_views[torch.randint(0, self.train_views.numel(), (n,), generator=self.generator)]
        pixels = torch.randint(0, npix, (n,), generator=self.generator)
        o, d = rays_for_pixels(self.geometry, views, pixels)
        return o.to(device), d.to(device), self.projections[views, pixels].to(device)


@dataclass
class LoopState:
    step: int = 0
    seconds: float = 0.0
    history: list[dict] = field(default_factory=list)


def make_optimizer(model: Field, lr: float) -> torch.optim.Adam:
    return torch.optim.Adam(model.param_groups(lr), betas=(0.9, 0.99))


def set_lr(opt: torch.optim.Optimizer, lr: float) -> None:
    for group in opt.param_groups:
        group["lr"] = lr * group.get("lr_scale", 1.0)


def train_step(
    model: Field,
    opt: torch.optim.Optimizer,
    batch: tuple[Tensor, Tensor, Tensor],
    render: Callable[[Tensor, Tensor], Tensor],
    tv: float,
) -> tuple[float, float]:
    """One optimiser step; returns (data loss, total loss)."""
    o, d, target = batch
    pred = render(o, d)
    data = torch.mean((pred - target) ** 2)
    loss = data + tv * model.tv() if tv > 0 and hasattr(model, "tv") else data
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    model.touch()  # fused Adam leaves the version counters: inference caches must know
    if hasattr(model, "clamp_"):
        model.clamp_()
    return float(data.detach()), float(loss.detach())


class Clock:
    """Training seconds: a stopwatch that evaluation pauses."""

    def __init__(self, already: float = 0.0) -> None:
        self.total, self.t0 = already, time.perf_counter()

    def __call__(self) -> float:
        return self.total + (time.perf_counter() - self.t0 if self.t0 is not None else 0.0)

    def pause(self) -> None:
        if self.t0 is not None:
            self.total += time.perf_counter() - self.t0
            self.t0 = None

    def resume(self) -> None:
        if self.t0 is None:
            self.t0 = time.perf_counter()


def sart_step(
    model: Field,
    batch: tuple[Tensor, Tensor, Tensor],
    render: Callable[[Tensor, Tensor], Tensor],
    unit_integrals: Callable[[Tensor, Tensor], Tensor],
    relax: float,
) -> float:
    """One SART-preconditioned step on the grid field (the same loss, a diagonal preconditioner).

    The line integrals are linear in theta (pred = A theta), so with row sums L = A 1 (`unit_integrals`: the
    integral of a field of ones) and column sums C = A^T 1 over the batch, the step
        theta += relax * A^T ((p - A theta) / L) / C
    is simultaneous ART (Andersen & Kak 1984) on the rays of the batch, i.e. ordered-subsets SART with random
    subsets: a gradient step on sum (p - A theta)^2 / L scaled per voxel by 1 / C. Returns the batch MSE.
    """
    o, d, target = batch
    pred = render(o, d)
    row = unit_integrals(o, d)  # [R]
    resid = torch.where(row > 0, (target - pred) / row.clamp(min=1e-12), torch.zeros_like(pred)).detach()
    theta = model.theta
    num = torch.autograd.grad(pred, theta, grad_outputs=resid, retain_graph=True)[0]
    col = torch.autograd.grad(pred, theta, grad_outputs=torch.ones_like(pred))[0]
    with torch.no_grad():
        theta += relax * torch.where(col > 0, num / col.clamp(min=1e-12), torch.zeros_like(num))
        model.clamp_()
    return float(torch.mean((pred.detach() - target) ** 2))
