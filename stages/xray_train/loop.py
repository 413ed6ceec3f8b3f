"""The step of `xray-train` on the shared loop (`model.loop.TrainingLoop`): random detector rays -> line integrals
through the field -> MSE.

Per step: `batch_rays` (view, pixel) pairs drawn uniformly from the training views, their rays
(radiance.xray.rays_for_pixels), line integrals through the field (model.xray.field_line_integrals: stratified,
jittered samples over the ray's chord of the box, Beer-Lambert in the compositing core), loss
mean((p - p_measured)^2) + tv * TV(field) (grid field only). Adam (or SART); the shared loop sets the learning
rate (exponential decay to `lr * lr_decay` over the run, progress = the larger of steps and seconds used), keeps
the budget, checkpoints (every `checkpoint_seconds`, at the end, on Ctrl-C) and recovers from non-finite losses.
The grid field is projected onto mu >= 0 after each step; coarse-to-fine upsampling at fixed fractions of the run
(`XraySteps.prepare`). Seconds count training only: evaluation pauses the clock.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import InitVar, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.progress import Progress
from nerfpipe.data.projections import ProjectionScene
from nerfpipe.data.rundir import MetricsLog
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule
from nerfpipe.model.xray import XRAY_FIELDS, field_line_integrals, field_volume, samples_for, save_xray_checkpoint
from nerfpipe.radiance.aabb import ray_aabb_intersect
from nerfpipe.radiance.ct_metrics import data_range, psnr_3d, psnr_projections, ssim_3d
from nerfpipe.radiance.fields import Field
from nerfpipe.radiance.metrics import psnr_from_mse
from nerfpipe.radiance.xray import XrayGeometry, detector_rays, rays_for_pixels, siddon_project
from nerfpipe.stages.xray_train.setup import Start, make_optimizer, samples_per_level

__all__ = ["Batches", "XraySteps", "budget", "evaluate", "evenly", "train_step", "sart_step"]


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


def train_step(
    model: Field,
    opt: torch.optim.Optimizer,
    batch: tuple[Tensor, Tensor, Tensor],
    render: Callable[[Tensor, Tensor], Tensor],
    tv: float,
) -> tuple[float, float] | None:
    """One optimiser step; returns (data loss, total loss), or None (and no update) when the loss is not finite."""
    o, d, target = batch
    pred = render(o, d)
    data = torch.mean((pred - target) ** 2)
    loss = data + tv * model.tv() if tv > 0 and hasattr(model, "tv") else data
    if not math.isfinite(float(loss.detach())):
        return None
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    model.touch()  # fused Adam leaves the version counters: inference caches must know
    if hasattr(model, "clamp_"):
        model.clamp_()
    return float(data.detach()), float(loss.detach())


def sart_step(
    model: Field,
    batch: tuple[Tensor, Tensor, Tensor],
    render: Callable[[Tensor, Tensor], Tensor],
    unit_integrals: Callable[[Tensor, Tensor], Tensor],
    relax: float,
) -> float | None:
    """One SART-preconditioned step on the grid field (the same loss, a diagonal preconditioner).

    The line integrals are linear in theta (pred = A theta), so with row sums L = A 1 (`unit_integrals`: the
    integral of a field of ones) and column sums C = A^T 1 over the batch, the step
        theta += relax * A^T ((p - A theta) / L) / C
    is simultaneous ART (Andersen & Kak 1984) on the rays of the batch, i.e. ordered-subsets SART with random
    subsets: a gradient step on sum (p - A theta)^2 / L scaled per voxel by 1 / C. Returns the batch MSE, or None
    (and no update) when it is not finite.
    """
    o, d, target = batch
    pred = render(o, d)
    mse = float(torch.mean((pred.detach() - target) ** 2))
    if not math.isfinite(mse):
        return None
    row = unit_integrals(o, d)  # [R]
    resid = torch.where(row > 0, (target - pred) / row.clamp(min=1e-12), torch.zeros_like(pred)).detach()
    theta = model.theta
    num = torch.autograd.grad(pred, theta, grad_outputs=resid, retain_graph=True)[0]
    col = torch.autograd.grad(pred, theta, grad_outputs=torch.ones_like(pred))[0]
    with torch.no_grad():
        theta += relax * torch.where(col > 0, num / col.clamp(min=1e-12), torch.zeros_like(num))
        model.clamp_()
    return mse


def budget(config: Any) -> Budget:
    return Budget(max_steps=config.max_steps, max_seconds=config.max_seconds)


def evenly(ids: tuple[int, ...], k: int) -> list[int]:
    """k of ids, evenly spaced (all of them when k >= len(ids))."""
    if k <= 0 or not ids:
        return []
    if k >= len(ids):
        return list(ids)
    return [ids[int(i)] for i in np.linspace(0, len(ids) - 1, k).round()]


@torch.no_grad()
def evaluate(model: Field, scene: ProjectionScene, test_views: list[int]) -> dict:
    """Sample the field on the grid; 3-D PSNR/SSIM (with ground truth) and re-projected test-view PSNR."""
    vol = field_volume(model, scene.grid).cpu()
    out = {"volume": vol}
    if scene.volume is not None:
        out["psnr_3d"] = psnr_3d(vol.numpy(), scene.volume)
        out["ssim_3d"] = ssim_3d(vol.numpy(), scene.volume)
    if test_views:
        nv, nu = scene.geometry.detector_shape
        pred = []
        for v in test_views:
            o, d = detector_rays(scene.geometry, v)
            pred.append(siddon_project(vol, scene.grid.spacing, scene.grid.center, o, d).reshape(nv, nu).numpy())
        out["test_proj_psnr"] = psnr_projections(np.stack(pred), scene.projections[test_views])
    return out


@dataclass(kw_only=True)
class XraySteps:
    """One X-ray run's mutable state and its step (`model.loop.Stepper`), from where it starts (`begin`: a new
    field or a checkpoint's, `stages.xray_train.setup.start`)."""

    config: Any  # stages.xray_train.Config
    scene: ProjectionScene
    begin: InitVar[Start]
    gen: torch.Generator
    device: torch.device
    metrics: MetricsLog
    progress: Progress
    model: Field = field(init=False)
    opt: torch.optim.Optimizer = field(init=False)
    step: int = field(init=False)
    lr_factor: float = field(init=False)
    level: int = field(init=False)
    """The level of the coarse-to-fine schedule the field is at."""
    lr: float = field(init=False)
    """The learning rate of the last step."""
    clock: Clock = field(init=False)
    """Training seconds (across resumes)."""

    def __post_init__(self, begin: Start) -> None:
        cfg, scene = self.config, self.scene
        self.model, self.opt, self.mu_ref, self.base_lr = begin.model, begin.opt, begin.mu_ref, begin.lr
        self.step, self.lr_factor, self.level, self.schedule = begin.step, begin.lr_factor, begin.level, begin.schedule
        self.clock = Clock(begin.seconds)
        self.samples = samples_per_level(scene, cfg.step_ratio, self.schedule)
        self.lr = Schedule(lr=begin.lr, decay=cfg.lr_decay).at(
            budget(cfg).fraction(begin.step, begin.seconds), begin.lr_factor
        )
        self.ckpt_path = Path(cfg.run_dir) / "checkpoint.pt"
        projections = torch.from_numpy(scene.projections).reshape(scene.geometry.n_views, -1)
        train_views = torch.as_tensor(scene.split("train"))
        self.batches = Batches(
            geometry=scene.geometry, projections=projections, train_views=train_views, generator=self.gen
        )
        self.test_views = evenly(scene.split("test"), cfg.eval_test_views)  # re-projected at each periodic evaluation
        every = cfg.eval_every  # training seconds between periodic evaluations
        self.next_eval = (math.floor(begin.seconds / every) + 1) * every if every > 0 else math.inf
        self._recent: list[float] = []
        self._box = torch.as_tensor(scene.grid.box, dtype=torch.float32, device=self.device)
        self._p_range = data_range(scene.projections[list(scene.split("train"))])
        self._task = self.progress.add_task("xray-train", total=cfg.max_seconds)

    def settings(self) -> LoopSettings:
        """The shared loop's settings from the config."""
        cfg = self.config
        return LoopSettings(
            name="xray-train",
            budget=budget(cfg),
            schedule=Schedule(lr=self.base_lr, decay=cfg.lr_decay),
            checkpoint_seconds=cfg.checkpoint_seconds,
            checkpoint_path=self.ckpt_path,
        )

    def prepare(self, fraction: float) -> bool:
        """Upsample the field at the schedule's fractions (a new optimiser); True when it did."""
        upsample_at = self.config.upsample_at
        upsampled = False
        while self.level < len(upsample_at) and fraction >= upsample_at[self.level]:
            self.level += 1
            XRAY_FIELDS[self.config.field].upsample(self.model, self.scene.grid, self.schedule[self.level])
            self.opt = make_optimizer(self.model, self.base_lr)
            upsampled = True
        return upsampled

    def train_step(self, lr: float) -> bool:
        self.lr = lr
        batch = self.batches.draw(self.config.batch_rays, self.device)
        if self.config.optimizer == "sart":
            data_loss = sart_step(self.model, batch, self._render, self._unit_integrals, lr)
        else:
            losses = train_step(self.model, self.opt, batch, self._render, self.config.tv)
            data_loss = losses[0] if losses is not None else None
        if data_loss is None:
            return False
        self._recent.append(data_loss)
        return True

    def _render(self, o: Tensor, d: Tensor) -> Tensor:
        return field_line_integrals(
            self.model, o, d, self._box, self.samples[self.level], jitter=True, generator=self.gen
        )

    def _unit_integrals(self, o: Tensor, d: Tensor) -> Tensor:
        """Line integrals of theta = 1 (mu = mu_ref) over the box: SART's row sums."""
        t0, t1, hit = ray_aabb_intersect(o, d, self._box)
        return torch.where(hit, (t1 - t0) * self.mu_ref, torch.zeros_like(t0))

    def log(self, lr: float) -> None:
        """A metrics row every log_every steps, with the volume's scores every eval_every training seconds."""
        cfg, clock = self.config, self.clock
        if not (self.step % cfg.log_every == 0 or clock() >= self.next_eval):
            return
        mean = float(np.mean(self._recent))
        row = {
            "step": self.step,
            "seconds": round(clock(), 3),
            "loss": mean,
            "train_psnr": round(psnr_from_mse(mean / self._p_range**2), 3),
            "lr": lr,
            "resolution": self.schedule[self.level],
        }
        self._recent = []
        if clock() >= self.next_eval:
            with clock.paused():
                scores = evaluate(self.model, self.scene, self.test_views)
            row.update({k: round(v, 4) for k, v in scores.items() if k != "volume"})
            self.next_eval += cfg.eval_every
        self.metrics.append(**row)
        if "psnr_3d" in row or "test_proj_psnr" in row:
            self.metrics.save()  # the curve so far is on disk while a long run goes on
        self.progress.update(self._task, completed=min(clock(), cfg.max_seconds))

    def snapshot(self) -> tuple[dict, dict]:
        return copy.deepcopy(self.model.state_dict()), copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[dict, dict]) -> None:
        model_state, opt_state = snapshot
        self.model.load_state_dict(model_state)
        self.opt.load_state_dict(opt_state)
        self.model.touch()

    def checkpoint(self, seconds: float) -> None:
        """checkpoint.pt and metrics.csv at the current step (periodic, and on Ctrl-C or SIGTERM)."""
        self.finish(seconds)
        self.metrics.save()

    def finish(self, seconds: float) -> None:
        """checkpoint.pt: the field, the optimiser and what `--resume` continues from (model.xray's format)."""
        save_xray_checkpoint(
            self.ckpt_path,
            self.model,
            self.opt,
            step=self.step,
            seconds=seconds,
            mu_ref=self.mu_ref,
            n_samples_render=samples_for(self.scene.grid, 0.5 * self.config.step_ratio),
            lr_factor=self.lr_factor,
            level=self.level,
            rng=self.gen.get_state(),
        )
