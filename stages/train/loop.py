"""The optimisation loop of `train`: its step on `model.loop.TrainingLoop` (the one loop every mode shares), the
coarse-to-fine schedule, evaluation and checkpoints.

Progress through the run is the larger of the step and the wall-clock fractions (max_steps, max_seconds), so a
time budget gets the whole schedule: the learning rate decays exponentially to `lr_decay` over it and the fast
grid is upsampled at the `upsample_at` fractions. Seconds spent on periodic evaluation are not training time
(the schedule, the budget and metrics.csv exclude them). A non-finite loss restores the last good state
(kept every 100 steps and at each upsample) and halves the learning rate; the third time the run stops.

Checkpoints: every `checkpoint_every` steps, every `checkpoint_seconds` of wall-clock time (so a killed run loses
at most that), at the end, and when `stop` (`data.stop`: SIGINT/SIGTERM) is raised, after which the loop raises
`data.errors.Interrupted` ("interrupted at step N after S s; continue with --resume").

Data-parallel (`parallel`, `model.distributed`): every rank draws the step's whole batch and renders its share;
the loss's per-ray terms are weighted by the share (n_r W / B), the priors and the depth term count alike on every
rank, and the gradients (field, background, appearance, cameras) are averaged before the TV gradient and the
optimiser steps. The loss's finiteness and the logged loss are the whole batch's. Rank 0 alone evaluates, logs and
writes checkpoints; every rank checks at each checkpoint that the parameters and the grid are still the same.
"""

from __future__ import annotations

import contextlib
import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.progress import Progress
from nerfpipe.data.rundir import MetricsLog
from nerfpipe.data.stop import StopRequest
from nerfpipe.model.camera_opt import CameraOpt
from nerfpipe.model.checkpoint import save_checkpoint
from nerfpipe.model.distributed import DataParallel
from nerfpipe.model.field_model import FieldModel
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingDiverged, TrainingLoop
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.fields import Field
from nerfpipe.radiance.metrics import psnr_from_mse
from nerfpipe.radiance.regularizers import depth_nll_loss
from nerfpipe.stages.train.config import Config
from nerfpipe.stages.train.views import DepthRays, Views

__all__ = ["TrainingDiverged", "Loop", "make_optimizer", "upsample_schedule", "evaluate_psnr"]

DEPTH_RAYS = 256
"""Sparse-point rays rendered per step for the depth loss (a quarter of the CPU photometric batch)."""
DEPTH_SIGMA = 0.02
"""Depth uncertainty of a structure-from-motion point, as a fraction of its distance (DS-NeRF's sigma)."""


TV_TEXELS = 4096
"""Random texels per plane in each step's total-variation estimate (`TensoRF.tv`)."""


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


def upsample_schedule(resolution: tuple[int, int], upsample_at: tuple[float, ...]) -> list[tuple[float, int]]:
    """(progress fraction, grid resolution) pairs: geometric steps from resolution[0] to resolution[1]."""
    r0, r1 = resolution
    n = len(upsample_at)
    if n == 0 or r0 == r1:
        return []
    res = [round(math.exp(math.log(r0) + (math.log(r1) - math.log(r0)) * (k + 1) / n)) for k in range(n)]
    return list(zip(upsample_at, res, strict=True))


@torch.no_grad()
def evaluate_psnr(
    model: FieldModel, views: Views, idx: Tensor, bg: Tensor, device: torch.device, rays: Callable | None = None
) -> float:
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
    """One training run's mutable state and its step (`model.loop.Stepper`); `run()` steps until the step or time
    budget is spent."""

    config: Config  # resolved (stages.train.defaults.resolve_defaults): no None left in it but final_eval_views
    model: FieldModel
    opt: torch.optim.Optimizer
    train: Views
    test: Views | None
    eval_px: Tensor | None  # [K] held-out rays for the periodic test PSNR
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
    _losses: list[float] = field(default_factory=list)
    cameras: CameraOpt | None = None  # pose refinement (train --refine-poses; model.camera_opt)
    depth_rays: DepthRays | None = None  # sparse-point depth supervision (train --depth-loss)
    parallel: DataParallel | None = None  # data-parallel runs (torchrun; model.distributed); None: one process
    _loop: TrainingLoop | None = None  # while run() runs
    _schedule: list[tuple[float, int]] = field(default_factory=list)  # upsampling still to come
    _task: Any = None  # the progress display's task
    _before_refine: tuple[int, dict] | None = None  # (step, field state) when the cameras first moved
    _rolled_back: bool = False  # the field went back to _before_refine (prepare() tells the loop once)

    def test_rays(self) -> Callable | None:
        """The map of test rays into the refined cameras' frame (None without pose refinement)."""
        return self.cameras.test_rays() if self.cameras is not None else None

    def elapsed(self) -> float:
        """Training seconds so far (across resumes, evaluation excluded)."""
        return self._loop.clock() if self._loop is not None else self.seconds_before

    def settings(self) -> LoopSettings:
        """The shared loop's settings from the train config."""
        cfg = self.config
        return LoopSettings(
            name="train",
            budget=Budget(max_steps=cfg.max_steps, max_seconds=cfg.max_seconds),
            schedule=Schedule(lr=cfg.lr, decay=cfg.lr_decay),
            checkpoint_every=cfg.checkpoint_every,
            checkpoint_seconds=cfg.checkpoint_seconds,
            checkpoint_path=self.ckpt_path,
        )

    def run(self) -> float:
        """Train until max_steps or max_seconds; refresh the occupancy grid; checkpoint. Returns seconds."""
        cfg = self.config
        self._schedule = upsample_schedule(cfg.fast.resolution, cfg.fast.upsample_at)
        agree = self.parallel.agree if self.parallel is not None else None
        self._loop = TrainingLoop(self.settings(), self, Clock(self.seconds_before), self.stop, agree)
        self._task = self.progress.add_task("train", total=cfg.max_seconds)
        self.model.field.train()
        self._check_same("at the start")
        return self._loop.run()

    def prepare(self, fraction: float) -> bool:
        """Fast fields: upsample at the schedule's fractions (a new optimiser), refresh the occupancy grid. True
        when the grid was upsampled, or the field rolled back since the last call (`_camera_step`)."""
        rolled_back, self._rolled_back = self._rolled_back, False
        if self.model.kind != "fast":
            return rolled_back
        upsampled = False
        while self._schedule and fraction >= self._schedule[0][0]:
            _, res = self._schedule.pop(0)
            if res > self.model.field.resolution:
                self.model.field.upsample(res)
                self.opt = make_optimizer(self.model, self.config.lr)
                upsampled = True
        self.model.grid.update(
            self.model.field.density, self.step, every=self.config.fast.occupancy_every, warmup_steps=64
        )
        return upsampled or rolled_back  # the loop keeps a new good state for its non-finite recovery

    def train_step(self, lr: float) -> bool:
        """One optimiser step on a random batch of rays; False (and no update) when the loss is not finite."""
        fast, model, par = self.config.fast, self.model, self.parallel
        idx = torch.randint(self.train.n_rays, (self.config.batch_rays,), generator=self.gen)
        o, d, rgb, alpha, view, bg, bg_all = self._rays(idx)
        target = over_background(rgb, alpha[:, None], bg.detach())
        with self._draws(idx.numel()):
            out = model.render(o, d, bg, train=True, gen=None, view=view)
        share = 1.0 if par is None else o.shape[0] * par.world.size / idx.numel()  # per-ray terms' weight
        loss = torch.mean((out["rgb"] - target) ** 2)
        mse = float(loss.detach())
        if "rgb_coarse" in out:
            loss = loss + torch.mean((out["rgb_coarse"] - target) ** 2)
        if share != 1.0:
            loss = loss * share
        if model.kind == "fast" and fast.density_l1 > 0:
            loss = loss + fast.density_l1 * model.field.density_l1()
        if fast.distortion:
            loss = loss + share * fast.distortion * model.distortion(out, o, d)
        if self.depth_rays is not None and fast.depth_loss:
            loss = loss + fast.depth_loss * self._depth_term(bg_all)
        samples = float(out["samples"])
        if par is None:
            if not math.isfinite(float(loss.detach())):
                return False
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
        else:
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            weight = o.shape[0] / idx.numel()
            total, mse, samples = par.average(
                self._reduced_params(), [float(loss.detach()) / par.world.size, mse * weight, samples]
            )
            if not math.isfinite(total):
                return False
        if model.kind == "fast" and fast.tv > 0:
            model.field.add_tv_grad_(fast.tv, TV_TEXELS, self.gen)
        self.opt.step()
        model.field.touch()  # fused Adam leaves the version counters: the field's inference caches must know
        if self.cameras is not None:
            self._camera_step()
        self._losses.append(mse)
        per_ray = samples / idx.numel()
        self.samples_per_ray = 0.9 * self.samples_per_ray + 0.1 * per_ray if self.step > 0 else per_ray
        if model.grid is not None:
            self.skip_fraction = model.grid.skip_fraction
        return True

    def _camera_step(self) -> None:
        """The cameras' step after the field's; the field's state is kept at the cameras' first move, and restored
        when the guard stops refinement (`model.camera_opt` "Rollback")."""
        cams, frac = self.cameras, self._loop.fraction()
        if self._before_refine is None and cams.moves(frac):  # the field has only seen the input cameras so far
            self._before_refine = (self.step + 1, self._field_state())
        cams.step(frac, step=self.step + 1)  # the guard records the step it acts at
        if cams.log.stopped_at == self.step + 1 and self._before_refine is not None:
            kept_at, state = self._before_refine
            self._restore_field_state(state)
            cams.log.rolled_back_to = kept_at
            self._rolled_back = True
            self._before_refine = None

    def _learned(self) -> dict[str, torch.nn.Module]:
        """What the field learned, by name: the field, background, appearance codes and occupancy grid (those the
        model has)."""
        m = self.model
        mods = {"field": m.field, "background": m.background, "appearance": m.appearance, "grid": m.grid}
        return {k: v for k, v in mods.items() if v is not None}

    def _field_state(self) -> dict[str, Any]:
        """A copy of `_learned`'s states, the field's grid resolution and the optimiser's state."""
        state = {k: copy.deepcopy(v.state_dict()) for k, v in self._learned().items()}
        resolution = getattr(self.model.field, "resolution", None)
        return state | {"resolution": resolution, "opt": copy.deepcopy(self.opt.state_dict())}

    def _restore_field_state(self, state: dict[str, Any]) -> None:
        """Back to `_field_state`'s copy and its optimiser state; when the grid was upsampled since, the copy is
        resampled to today's resolution and the optimiser starts afresh (as at an upsampling)."""
        field = self.model.field
        now = getattr(field, "resolution", None)
        resampled = now != state["resolution"]
        if resampled:
            field.upsample(state["resolution"])  # the copy's shapes, then its values
        for key, mod in self._learned().items():
            mod.load_state_dict(state[key])
        if resampled:
            field.upsample(now)
        self.opt = make_optimizer(self.model, self.config.lr)
        if not resampled:
            self.opt.load_state_dict(state["opt"])
        field.touch()

    def _rays(self, idx: Tensor) -> tuple[Tensor, ...]:
        """The batch idx [B] -> this rank's rays o, d [b, 3], rgb [b, 3], alpha [b], view [b] and background
        ([b, 3] or [3]), and the whole batch's background (one process: b = B). The background colours are drawn
        for the whole batch on every rank (the same generator as one process)."""
        if self.parallel is None:
            o, d, rgb, alpha = self.train.batch(idx, self.device)
            view = self.train.view[idx].to(self.device)  # [B] each ray's training view
            if self._refining():
                o, d = self.cameras(o, d, view)
            rand = self.train.random_behind(idx, alpha == 0)  # [B]
            bg = self.model.background.train_colour(o.shape[0], self.gen, random=rand)  # [B, 3] or [3]
            return o, d, rgb, alpha, view, bg, bg
        rand = self.train.random_behind(idx, (self.train.rgba[idx, 3] == 0).to(self.device))  # [B] as above
        bg_all = self.model.background.train_colour(idx.numel(), self.gen, random=rand)
        mine = self.parallel.world.share(idx.numel())
        o, d, rgb, alpha = self.train.batch(idx[mine], self.device)
        view = self.train.view[idx[mine]].to(self.device)
        if self._refining():
            o, d = self.cameras(o, d, view)
        return o, d, rgb, alpha, view, (bg_all[mine] if bg_all.ndim == 2 else bg_all), bg_all

    def _refining(self) -> bool:
        """Whether rays go through the cameras' corrections: with pose refinement, until the guard stops it (then
        the corrections are zero and the rays are the input cameras', as in a run without refinement)."""
        return self.cameras is not None and self.cameras.log.stopped_at is None

    def _draws(self, total: int):
        """The renderer's random draws of this rank's rays (`DataParallel.share_draws`; one process: as they come).
        The fast field draws one jitter a ray; the vanilla field's two draws get rank-distinct places."""
        if self.parallel is None:
            return contextlib.nullcontext()
        per_ray = 1 if self.model.kind == "fast" else self.model.field.n_coarse + self.model.field.n_fine
        return self.parallel.share_draws(total, self.parallel.world.share(total), per_ray)

    def _reduced_params(self) -> list[Tensor]:
        """Every parameter a step's backward reaches: the optimiser's (field, background, appearance) and the
        cameras' corrections."""
        params = [p for g in self.opt.param_groups for p in g["params"]]
        if self.cameras is not None:
            params += [p for p in self.cameras.parameters() if p.requires_grad]
        return params

    def _depth_term(self, bg: Tensor) -> Tensor:
        """DS-NeRF's loss on DEPTH_RAYS random rays through the training cameras' sparse points."""
        rays = self.depth_rays
        k = torch.randint(rays.depth.shape[0], (DEPTH_RAYS,), generator=self.gen)
        o, d, depth, view = (t[k].to(self.device) for t in (rays.o, rays.d, rays.depth, rays.view))
        if self._refining():
            o, d = self.cameras(o, d, view)
        if bg.ndim == 2:  # per-ray colours of the photometric batch, reused (the colour does not enter the loss)
            bg = bg[torch.arange(o.shape[0], device=bg.device) % bg.shape[0]]
        out = self.model.render(o, d, bg.detach(), train=True, gen=None, view=view)
        return depth_nll_loss(
            out["weights"], out["t_starts"], out["t_ends"], out["ray_indices"], depth, DEPTH_SIGMA * depth
        )

    def snapshot(self) -> tuple[dict, dict]:
        return copy.deepcopy(self.model.field.state_dict()), copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[dict, dict]) -> None:
        field_state, opt_state = snapshot
        self.model.field.load_state_dict(field_state)
        self.opt.load_state_dict(opt_state)

    def log(self, lr: float) -> None:
        """A metrics row every log_every steps, with the held-out PSNR every eval_every steps."""
        cfg = self.config
        if self.parallel is not None and not self.parallel.writer:  # rank 0 logs
            self._losses = []
            return
        evaluate = self.test is not None and cfg.eval_every > 0 and self.step % cfg.eval_every == 0
        if not (self.step % cfg.log_every == 0 or evaluate):
            return
        self.model.field.eval()
        mean_loss = float(np.mean(self._losses))
        row = {
            "step": self.step,
            "seconds": round(self.elapsed(), 3),
            "loss": f"{mean_loss:.6g}",
            "train_psnr": f"{psnr_from_mse(mean_loss):.3f}",
            "lr": f"{lr:.4g}",
            "samples_per_ray": f"{self.samples_per_ray:.2f}",
            "skip_fraction": f"{self.skip_fraction:.4f}",
        }
        if evaluate:
            with self._loop.clock.paused():
                t_eval = time.perf_counter()
                bg = self.model.background.eval_colour().detach()
                psnr = evaluate_psnr(self.model, self.test, self.eval_px, bg, self.device, self.test_rays())
                row["test_psnr"] = f"{psnr:.3f}"
                spent = time.perf_counter() - t_eval
            self.eval_rays_per_second = self.eval_px.numel() / max(spent, 1e-6)
        self.model.field.train()
        self.metrics.append(**row)
        self._losses = []
        self.progress.update(
            self._task,
            completed=min(row["seconds"], cfg.max_seconds),
            description=f"train step {self.step}, {row['train_psnr']} dB",
        )

    def checkpoint(self, seconds: float) -> None:
        """checkpoint.pt and metrics.csv at the current step (periodic, and on Ctrl-C or SIGTERM)."""
        self._save(seconds)
        if self.parallel is None or self.parallel.writer:
            self.metrics.save()

    def finish(self, seconds: float) -> None:
        """The final occupancy grid and checkpoint."""
        if self.model.grid is not None:
            # Every cell once more: the saved grid must match the final field (render and mesh skip by it), not a
            # partial refresh from before the last steps moved the surface.
            self.model.grid.update(self.model.field.density, self.step, full=True, points_per_cell=4)
        self._save(seconds)

    def _check_same(self, where: str) -> None:
        """Data-parallel: stop when the ranks' parameters or occupancy grids differ (`DataParallel.check_same`)."""
        if self.parallel is not None:
            named = {f"field.{k}": v for k, v in self.model.field.state_dict().items()}
            if self.model.grid is not None:
                named |= {f"occupancy.{k}": v for k, v in self.model.grid.state_dict().items()}
            if self.cameras is not None:
                named["cameras"] = self.cameras.raw
            self.parallel.check_same(named, where)

    def _save(self, seconds: float) -> None:
        self._check_same(f"at step {self.step}")
        if self.parallel is not None and not self.parallel.writer:  # rank 0 writes
            return
        self.ckpt_sha256 = save_checkpoint(
            self.ckpt_path, self.model, self.opt, self.step, seconds, self.lr_factor, self.gen.get_state(), self.cameras
        )
