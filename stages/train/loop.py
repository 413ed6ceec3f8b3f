"""The optimisation loop of `train`: schedules, one step, recovery from non-finite losses, logging, checkpoints.

Progress through the run is the larger of the step and the wall-clock fractions (max_steps, max_seconds), so a
time budget gets the whole schedule: the learning rate decays exponentially to `lr_decay` over it and the fast
grid is upsampled at the `upsample_at` fractions. Seconds spent on periodic evaluation are not training time
(the schedule, the budget and metrics.csv exclude them). A non-finite loss restores the last good state
(kept every 100 steps and at each upsample) and halves the learning rate; the third time the run stops.

Checkpoints: every `checkpoint_every` steps, every `checkpoint_seconds` of wall-clock time (so a killed run loses
at most that), at the end, and when `stop` (`data.stop`: SIGINT/SIGTERM) is raised, after which the loop raises
`data.errors.Interrupted` ("interrupted at step N after S s; continue with --resume").
"""

from __future__ import annotations

import copy
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from data.errors import Interrupted
from data.progress import Progress
from data.rundir import MetricsLog
from data.stop import StopRequest
from model.camera_opt import CameraOpt
from model.checkpoint import save_checkpoint
from model.field_model import FieldModel
from radiance.compositing import over_background
from radiance.fields import Field
from radiance.metrics import psnr_from_mse
from radiance.regularizers import depth_nll_loss
from stages.train.views import Views

__all__ = ["TrainingDiverged", "Loop", "make_optimizer", "upsample_schedule", "evaluate_psnr", "DepthRays"]

DEPTH_RAYS = 256
"""Sparse-point rays rendered per step for the depth loss (a quarter of the CPU photometric batch)."""
DEPTH_SIGMA = 0.02
"""Depth uncertainty of a structure-from-motion point, as a fraction of its distance (DS-NeRF's sigma)."""


@dataclass(frozen=True)
class DepthRays:
    """Rays from training cameras through their observed sparse points: o, d [K, 3], depth [K], view [K]."""

    o: Tensor
    d: Tensor
    depth: Tensor
    view: Tensor


TV_TEXELS = 4096
"""Random texels per plane in each step's total-variation estimate (`TensoRF.tv`)."""


class TrainingDiverged(RuntimeError):
    """The loss went non-finite repeatedly, even after restoring the last good state with a lower LR."""


def make_optimizer(model: FieldModel | Field, lr: float, *, fused: bool = True) -> torch.optim.Adam:
    """Adam over the field (and a learned background colour, at lr); `fused` (one kernel per group, the
    same update up to float rounding) is the fast path: the plain per-tensor loop took half of a fast-field
    step on CPU (lego_100, 2 cores: 14.6 -> 23.4 steps/s at the final grid; 1599 -> 1989 steps in 120 s).
    fused=False is its plain twin (tests)."""
    field, extra = (model.field, model.background.params()) if isinstance(model, FieldModel) else (model, [])
    groups = field.param_groups(lr)
    if extra:
        groups.append({"params": extra, "lr": lr, "lr_scale": 1.0})
    if isinstance(model, FieldModel) and model.appearance is not None:
        groups += model.appearance.param_groups(lr)
    return torch.optim.Adam(groups, betas=(0.9, 0.99), fused=fused)


def _set_lr(opt: torch.optim.Optimizer, base: float) -> None:
    for g in opt.param_groups:
        g["lr"] = base * g.get("lr_scale", 1.0)


def upsample_schedule(resolution: tuple[int, int], upsample_at: tuple[float, ...]) -> list[tuple[float, int]]:
    """(progress fraction, grid resolution) pairs: geometric steps from resolution[0] to resolution[1]."""
    r0, r1 = resolution
    n = len(upsample_at)
    if n == 0 or r0 == r1:
        return []
    res = [round(math.exp(math.log(r0) + (math.log(r1) - math.log(r0)) * (k + 1) / n)) for k in range(n)]
    return list(zip(upsample_at, res, strict=True))


@torch.no_grad()
def evaluate_psnr(model: FieldModel, views: Views, idx: Tensor, bg: Tensor, device: torch.device,
                  rays: Callable | None = None) -> float:  # fmt: skip
    """PSNR over the rays idx [K] of `views`, photos with alpha composited on bg [3]; `rays` maps (o, d) into
    the frame of refined cameras (`CameraOpt.test_rays`; None: as given)."""
    se, n, chunk = 0.0, 0, model.chunk
    for i in range(0, idx.numel(), chunk):
        o, d, rgb, alpha = views.batch(idx[i : i + chunk], device)
        if rays is not None:
            o, d = rays(o, d)
        pred = model.render(o, d, bg, train=False)["rgb"]
        se += float(((pred - over_background(rgb, alpha[:, None], bg)) ** 2).sum())
        n += pred.numel()
    return psnr_from_mse(se / max(n, 1))


@dataclass
class Loop:
    """One training run's mutable state; `run()` steps until the step or time budget is spent."""

    config: Any  # stages.train.Config
    model: FieldModel
    opt: torch.optim.Optimizer
    base_lr: float
    train: Views
    test: Views | None
    eval_px: Tensor | None  # [K] held-out rays for the periodic test PSNR
    batch_rays: int
    gen: torch.Generator
    device: torch.device
    metrics: MetricsLog
    ckpt_path: Path
    progress: Progress
    step: int = 0
    seconds_before: float = 0.0
    lr_factor: float = 1.0
    samples_per_ray: float = 0.0
    skip_fraction: float = 0.0
    eval_rays_per_second: float | None = None
    stop: StopRequest | None = None  # polled between steps (data.stop)
    ckpt_sha256: str | None = None  # of the last checkpoint written
    _ckpt_wall: float = 0.0  # time.perf_counter() at the last checkpoint
    _paused: float = 0.0
    _t_start: float = 0.0
    _losses: list[float] = field(default_factory=list)
    cameras: CameraOpt | None = None  # pose refinement (train --refine-poses; model.camera_opt)
    depth_rays: DepthRays | None = None  # sparse-point depth supervision (train --depth-loss)

    def test_rays(self) -> Callable | None:
        """The map of test rays into the refined cameras' frame (None without pose refinement)."""
        return self.cameras.test_rays() if self.cameras is not None else None

    def elapsed(self) -> float:
        """Training seconds so far (across resumes, evaluation excluded)."""
        return self.seconds_before + time.perf_counter() - self._t_start - self._paused

    def run(self) -> float:
        """Train until max_steps or max_seconds; refresh the occupancy grid; checkpoint. Returns seconds."""
        cfg = self.config
        schedule = upsample_schedule(cfg.resolution, cfg.upsample_at)
        self._t_start = self._ckpt_wall = time.perf_counter()
        good = self._snapshot()
        failures = 0
        task = self.progress.add_task("train", total=cfg.max_seconds)
        self.model.field.train()
        while self.step < cfg.max_steps:
            if self.stop is not None and self.stop.signum is not None:
                self._interrupted()
            frac = max(self.step / max(cfg.max_steps, 1), self.elapsed() / cfg.max_seconds)
            if frac >= 1.0:
                break
            if self.model.kind == "fast":
                while schedule and frac >= schedule[0][0]:
                    _, res = schedule.pop(0)
                    if res > self.model.field.resolution:
                        self.model.field.upsample(res)
                        self.opt = make_optimizer(self.model, self.base_lr)
                        good = self._snapshot()
                self.model.grid.update(self.model.field.density, self.step, every=cfg.occupancy_every,
                                       warmup_steps=64)  # fmt: skip
            lr = self.base_lr * self.lr_factor * cfg.lr_decay**frac
            _set_lr(self.opt, lr)
            if not self._step():
                failures += 1
                good = self._recover(good, failures)
                continue
            if self.step % 100 == 0:
                good = self._snapshot()
            self._log(lr, task)
            every_s = getattr(cfg, "checkpoint_seconds", 0.0)
            if self.step % cfg.checkpoint_every == 0 or (
                every_s > 0 and time.perf_counter() - self._ckpt_wall >= every_s
            ):
                self._checkpoint()
                self.metrics.save()
        seconds = self.elapsed()
        if self.model.grid is not None:
            # Every cell once more: the saved grid must match the final field (render and mesh skip by it), not a
            # partial refresh from before the last steps moved the surface.
            self.model.grid.update(self.model.field.density, self.step, full=True, points_per_cell=4)
        self._checkpoint(seconds)
        return seconds

    def _step(self) -> bool:
        """One optimiser step on a random batch of rays; False (and no update) when the loss is not finite."""
        cfg, model = self.config, self.model
        idx = torch.randint(self.train.n_rays, (self.batch_rays,), generator=self.gen)
        o, d, rgb, alpha = self.train.batch(idx, self.device)
        view = self.train.view[idx].to(self.device)  # [B] each ray's training view
        if self.cameras is not None:
            o, d = self.cameras(o, d, view)
        bg = model.background.train_colour(o.shape[0], self.gen, transparent=alpha == 0)  # [B, 3] or [3]
        target = over_background(rgb, alpha[:, None], bg.detach())
        out = model.render(o, d, bg, train=True, gen=None, view=view)
        loss = torch.mean((out["rgb"] - target) ** 2)
        mse = float(loss.detach())
        if "rgb_coarse" in out:
            loss = loss + torch.mean((out["rgb_coarse"] - target) ** 2)
        if model.kind == "fast" and cfg.density_l1 > 0:
            loss = loss + cfg.density_l1 * model.field.density_l1()
        if cfg.distortion:
            loss = loss + cfg.distortion * model.distortion(out, o, d)
        if self.depth_rays is not None and cfg.depth_loss:
            loss = loss + cfg.depth_loss * self._depth_term(bg)
        if not math.isfinite(float(loss.detach())):
            return False
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        if model.kind == "fast" and (cfg.tv or 0) > 0:
            model.field.add_tv_grad_(cfg.tv, TV_TEXELS, self.gen)
        self.opt.step()
        model.field.touch()  # fused Adam leaves the version counters: the field's inference caches must know
        if self.cameras is not None:
            frac = max(self.step / max(cfg.max_steps, 1), self.elapsed() / cfg.max_seconds)
            self.cameras.step(frac, step=self.step + 1)  # the guard records the step it acts at
        self.step += 1
        self._losses.append(mse)
        per_ray = float(out["samples"]) / o.shape[0]
        self.samples_per_ray = 0.9 * self.samples_per_ray + 0.1 * per_ray if self.step > 1 else per_ray
        if model.grid is not None:
            self.skip_fraction = model.grid.skip_fraction
        return True

    def _depth_term(self, bg: Tensor) -> Tensor:
        """DS-NeRF's loss on DEPTH_RAYS random rays through the training cameras' sparse points."""
        rays = self.depth_rays
        k = torch.randint(rays.depth.shape[0], (DEPTH_RAYS,), generator=self.gen)
        o, d, depth, view = (t[k].to(self.device) for t in (rays.o, rays.d, rays.depth, rays.view))
        if self.cameras is not None:
            o, d = self.cameras(o, d, view)
        if bg.ndim == 2:  # per-ray colours of the photometric batch, reused (the colour does not enter the loss)
            bg = bg[torch.arange(o.shape[0], device=bg.device) % bg.shape[0]]
        out = self.model.render(o, d, bg.detach(), train=True, gen=None, view=view)
        return depth_nll_loss(out["weights"], out["t_starts"], out["t_ends"], out["ray_indices"], depth,
                              DEPTH_SIGMA * depth)  # fmt: skip

    def _snapshot(self) -> tuple[dict, dict, int]:
        return copy.deepcopy(self.model.field.state_dict()), copy.deepcopy(self.opt.state_dict()), self.step

    def _recover(self, good: tuple[dict, dict, int], failures: int) -> tuple[dict, dict, int]:
        if failures >= 3:
            raise TrainingDiverged(f"loss is not finite at step {self.step} after {failures} restores with lower "
                                   f"learning rates; last checkpoint kept in {self.ckpt_path}")  # fmt: skip
        field_state, opt_state, self.step = good
        self.model.field.load_state_dict(field_state)
        self.opt.load_state_dict(opt_state)
        self.lr_factor *= 0.5
        print(f"train: non-finite loss; restored step {self.step}, learning rate x{self.lr_factor}", file=sys.stderr)
        return good

    def _log(self, lr: float, task: Any) -> None:
        """A metrics row every log_every steps, with the held-out PSNR every eval_every steps."""
        cfg = self.config
        evaluate = self.test is not None and cfg.eval_every > 0 and self.step % cfg.eval_every == 0
        if not (self.step % cfg.log_every == 0 or evaluate):
            return
        self.model.field.eval()
        mean_loss = float(np.mean(self._losses))
        row = {"step": self.step, "seconds": round(self.elapsed(), 3), "loss": f"{mean_loss:.6g}",
               "train_psnr": f"{psnr_from_mse(mean_loss):.3f}", "lr": f"{lr:.4g}",
               "samples_per_ray": f"{self.samples_per_ray:.2f}",
               "skip_fraction": f"{self.skip_fraction:.4f}"}  # fmt: skip
        if evaluate:
            t_eval = time.perf_counter()
            bg = self.model.background.eval_colour().detach()
            psnr = evaluate_psnr(self.model, self.test, self.eval_px, bg, self.device, self.test_rays())
            row["test_psnr"] = f"{psnr:.3f}"
            spent = time.perf_counter() - t_eval
            self._paused += spent
            self.eval_rays_per_second = self.eval_px.numel() / max(spent, 1e-6)
        self.model.field.train()
        self.metrics.append(**row)
        self._losses = []
        self.progress.update(task, completed=min(row["seconds"], cfg.max_seconds),
                             description=f"train step {self.step}, {row['train_psnr']} dB")  # fmt: skip

    def _checkpoint(self, seconds: float | None = None) -> None:
        seconds = self.elapsed() if seconds is None else seconds
        self.ckpt_sha256 = save_checkpoint(self.ckpt_path, self.model, self.opt, self.step, seconds, self.lr_factor,
                                           self.gen.get_state(), self.cameras)  # fmt: skip
        self._ckpt_wall = time.perf_counter()

    def _interrupted(self) -> None:
        """Save the current step (checkpoint, metrics) and stop with one line."""
        seconds = self.elapsed()
        self._checkpoint(seconds)
        self.metrics.save()
        raise Interrupted(f"interrupted ({self.stop.name}) at step {self.step} after {seconds:.1f} s; continue with "
                          f"--resume (checkpoint {self.ckpt_path})", self.stop.signum)  # fmt: skip
