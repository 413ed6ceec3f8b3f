"""The optimisation loop of `train`: its step on `model.loop.TrainingLoop` (the one loop every mode shares), with the
hooks a method or an option plugs in (`model.methods.hooks.Hook`), evaluation and checkpoints.

`Loop` holds only what every run has: the method's model and its optimiser, the photos, the generator, the metrics,
the checkpoint, and data-parallel averaging. The rest is hooks: the density field's upsampling, occupancy refresh
and priors (`model.methods.density.hooks`), pose refinement (`stages.train.refine`).

Progress through the run is the larger of the step and the wall-clock fractions (max_steps, max_seconds), so a
time budget gets the whole schedule: the learning rate decays exponentially to `lr_decay` over it. Seconds spent on
periodic evaluation are not training time (the schedule, the budget and metrics.csv exclude them). A non-finite
loss restores the last good state (kept every 100 steps and whenever a hook replaced the model) and halves the
learning rate; the third time the run stops.

Checkpoints: every `checkpoint_every` steps, every `checkpoint_seconds` of wall-clock time (so a killed run loses
at most that), at the end, and when `stop` (`data.stop`: SIGINT/SIGTERM) is raised, after which the loop raises
`data.errors.Interrupted` ("interrupted at step N after S s; continue with --resume").

Data-parallel (`parallel`, `model.distributed`): every rank draws the step's whole batch and renders its share;
the loss's per-ray terms are weighted by the share (n_r W / B), the priors and the depth term count alike on every
rank, and the gradients (the optimiser's and the hooks' parameters) are averaged before the hooks' after-backward
work and the optimiser's step. The loss's finiteness and the logged loss are the whole batch's. Rank 0 alone
evaluates, logs and writes checkpoints; every rank checks at each checkpoint that the learned state is the same.
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
from nerfpipe.model.checkpoint import save_checkpoint
from nerfpipe.model.distributed import DataParallel
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingDiverged, TrainingLoop
from nerfpipe.model.methods import Batch, Hook, Method, TrainModel
from nerfpipe.model.views import Views
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.metrics import psnr_from_mse
from nerfpipe.stages.train.config import Config

__all__ = ["TrainingDiverged", "Loop", "make_optimizer", "evaluate_psnr"]


def make_optimizer(model: TrainModel, lr: float, *, fused: bool = True) -> torch.optim.Adam:
    """Adam over the model's parameter groups (`TrainModel.param_groups`); `fused` (one kernel per group, the same
    update up to float rounding) is the fast path: the plain per-tensor loop took half of a density-field step on
    CPU (docs/DESIGN.md). fused=False is its plain twin (tests)."""
    return torch.optim.Adam(model.param_groups(lr), betas=(0.9, 0.99), fused=fused)


@torch.no_grad()
def evaluate_psnr(
    model: TrainModel, views: Views, idx: Tensor, bg: Tensor, device: torch.device, rays: Callable | None = None
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
    """One training run's mutable state and its step (`model.loop.Stepper`, `model.methods.hooks.LoopState`);
    `run()` steps until the step or time budget is spent."""

    config: Config  # resolved (stages.train.defaults.resolve_defaults): no None left in it but final_eval_views
    method: Method
    model: TrainModel
    opt: torch.optim.Optimizer
    train: Views
    test: Views | None
    eval_px: Tensor | None  # [K] held-out rays for the periodic test PSNR
    gen: torch.Generator
    device: torch.device
    metrics: MetricsLog
    ckpt_path: Path
    progress: Progress
    hooks: list[Hook] = field(default_factory=list)
    step: int = 0
    seconds_before: float = 0.0
    lr_factor: float = 1.0
    parallel: DataParallel | None = None  # data-parallel runs (torchrun; model.distributed); None: one process
    stop: StopRequest | None = None  # polled between steps (data.stop)
    ckpt_sha256: str | None = None  # of the last checkpoint written
    samples_per_ray: float = 0.0
    eval_rays_per_second: float | None = None
    _losses: list[float] = field(default_factory=list)
    _loop: TrainingLoop | None = None  # while run() runs
    _task: Any = None  # the progress display's task

    def test_rays(self) -> Callable | None:
        """The map of held-out rays into the frame the model is trained in (a hook's `eval_rays`: pose refinement's
        refined cameras), or None."""
        maps = [m for hook in self.hooks if (m := hook.eval_rays()) is not None]
        return maps[0] if maps else None

    # ---- LoopState (what hooks use)
    def fraction(self) -> float:
        return self._loop.fraction()

    def elapsed(self) -> float:
        """Training seconds so far (across resumes, evaluation excluded)."""
        return self._loop.clock() if self._loop is not None else self.seconds_before

    def transform_rays(self, o: Tensor, d: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        for hook in self.hooks:
            o, d = hook.rays(self, o, d, view)
        return o, d

    def rebuild_optimizer(self, state: dict | None = None) -> None:
        self.opt = make_optimizer(self.model, self.config.lr)
        if state is not None:
            self.opt.load_state_dict(state)

    def snapshot(self) -> tuple[Any, dict]:
        """The model's learned state and a copy of the optimiser's."""
        return self.model.snapshot(), copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[Any, dict]) -> None:
        """Back to `snapshot`; a new optimiser (its state lost) when the model's shapes changed since."""
        state, opt_state = snapshot
        resampled = self.model.restore(state)
        self.rebuild_optimizer(None if resampled else opt_state)

    # ---- the run
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
        """Train until max_steps or max_seconds; checkpoint. Returns seconds."""
        agree = self.parallel.agree if self.parallel is not None else None
        self._loop = TrainingLoop(self.settings(), self, Clock(self.seconds_before), self.stop, agree)
        self._task = self.progress.add_task("train", total=self.config.max_seconds)
        self.model.train_mode(True)
        self._check_same("at the start")
        return self._loop.run()

    def prepare(self, fraction: float) -> bool:
        """Every hook's schedule work before a step (upsampling, grid refresh, a rollback to tell); True when one of
        them replaced the model or the optimiser."""
        changed = [hook.prepare(self, fraction) for hook in self.hooks]
        return any(changed)

    def train_step(self, lr: float) -> bool:
        """One optimiser step on a random batch of rays; False (and no update) when the loss is not finite."""
        model, par = self.model, self.parallel
        idx = self._draw(self.config.batch_rays)
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
        batch = Batch(o=o, d=d, view=view, background=bg, background_all=bg_all, share=share)
        for hook in self.hooks:
            term = hook.loss(self, batch, out)
            if term is not None:
                loss = loss + term
        samples = float(out["samples"]) if "samples" in out else 0.0
        self.opt.zero_grad(set_to_none=True)
        if par is None:
            if not math.isfinite(float(loss.detach())):
                return False
            loss.backward()
        else:
            loss.backward()
            weight = o.shape[0] / idx.numel()
            total, mse, samples = par.average(
                self._reduced_params(), [float(loss.detach()) / par.world.size, mse * weight, samples]
            )
            if not math.isfinite(total):
                return False
        for hook in self.hooks:
            hook.after_backward(self)
        self.opt.step()
        model.after_step()
        for hook in self.hooks:
            hook.after_step(self)
        self._losses.append(mse)
        per_ray = samples / idx.numel()
        self.samples_per_ray = 0.9 * self.samples_per_ray + 0.1 * per_ray if self.step > 0 else per_ray
        return True

    def _draw(self, n: int) -> Tensor:
        """The step's n ray indices [n]: the first hook's that draws them (`Hook.draw`), else uniform over every
        training pixel."""
        for hook in self.hooks:
            idx = hook.draw(self, n)
            if idx is not None:
                return idx
        return torch.randint(self.train.n_rays, (n,), generator=self.gen)

    def _rays(self, idx: Tensor) -> tuple[Tensor, ...]:
        """The batch idx [B] -> this rank's rays o, d [b, 3], rgb [b, 3], alpha [b], view [b] and background
        ([b, 3] or [3]), and the whole batch's background (one process: b = B). The background colours are drawn
        for the whole batch on every rank (the same generator as one process)."""
        if self.parallel is None:
            o, d, rgb, alpha = self.train.batch(idx, self.device)
            view = self.train.view[idx].to(self.device)  # [B] each ray's training view
            o, d = self.transform_rays(o, d, view)
            rand = self.train.random_behind(idx, alpha == 0)  # [B]
            bg = self.model.background.train_colour(o.shape[0], self.gen, random=rand)  # [B, 3] or [3]
            return o, d, rgb, alpha, view, bg, bg
        rand = self.train.random_behind(idx, (self.train.rgba[idx, 3] == 0).to(self.device))  # [B] as above
        bg_all = self.model.background.train_colour(idx.numel(), self.gen, random=rand)
        mine = self.parallel.world.share(idx.numel())
        o, d, rgb, alpha = self.train.batch(idx[mine], self.device)
        view = self.train.view[idx[mine]].to(self.device)
        o, d = self.transform_rays(o, d, view)
        return o, d, rgb, alpha, view, (bg_all[mine] if bg_all.ndim == 2 else bg_all), bg_all

    def _draws(self, total: int):
        """The renderer's random draws of this rank's rays (`DataParallel.share_draws`; one process: as they come)."""
        if self.parallel is None:
            return contextlib.nullcontext()
        share = self.parallel.world.share(total)
        return self.parallel.share_draws(total, share, self.model.random_draws_per_ray)

    def _reduced_params(self) -> list[Tensor]:
        """Every parameter a step's backward reaches: the optimiser's and the hooks' (camera corrections)."""
        params = [p for g in self.opt.param_groups for p in g["params"]]
        return params + [p for hook in self.hooks for p in hook.parameters()]

    def log(self, lr: float) -> None:
        """A metrics row every log_every steps, with the held-out PSNR every eval_every steps."""
        cfg = self.config
        if self.parallel is not None and not self.parallel.writer:  # rank 0 logs
            self._losses = []
            return
        evaluate = self.test is not None and cfg.eval_every > 0 and self.step % cfg.eval_every == 0
        if not (self.step % cfg.log_every == 0 or evaluate):
            return
        self.model.train_mode(False)
        mean_loss = float(np.mean(self._losses))
        row = {
            "step": self.step,
            "seconds": round(self.elapsed(), 3),
            "loss": f"{mean_loss:.6g}",
            "train_psnr": f"{psnr_from_mse(mean_loss):.3f}",
            "lr": f"{lr:.4g}",
            "samples_per_ray": f"{self.samples_per_ray:.2f}",
        }
        for hook in self.hooks:
            row.update(hook.metrics())
        if evaluate:
            with self._loop.clock.paused():
                t_eval = time.perf_counter()
                bg = self.model.background.eval_colour().detach()
                psnr = evaluate_psnr(self.model, self.test, self.eval_px, bg, self.device, self.test_rays())
                row["test_psnr"] = f"{psnr:.3f}"
                spent = time.perf_counter() - t_eval
            self.eval_rays_per_second = self.eval_px.numel() / max(spent, 1e-6)
        self.model.train_mode(True)
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
        """The hooks' final touches (the occupancy grid over every cell) and the final checkpoint."""
        for hook in self.hooks:
            hook.finish(self)
        self._save(seconds)

    def _check_same(self, where: str) -> None:
        """Data-parallel: stop when the ranks' learned states differ (`DataParallel.check_same`)."""
        if self.parallel is not None:
            named = {
                f"{key}.{name}": value
                for key, module in self.model.learned().items()
                for name, value in module.state_dict().items()
                if isinstance(value, Tensor)
            }
            for hook in self.hooks:
                named |= hook.fingerprint()
            self.parallel.check_same(named, where)

    def _save(self, seconds: float) -> None:
        self._check_same(f"at step {self.step}")
        if self.parallel is not None and not self.parallel.writer:  # rank 0 writes
            return
        extra = {k: v for hook in self.hooks for k, v in hook.checkpoint().items()}
        progress = {"step": self.step, "seconds": seconds, "lr_factor": self.lr_factor, "rng": self.gen.get_state()}
        self.ckpt_sha256 = save_checkpoint(
            self.ckpt_path,
            method=self.method.name,
            entries=self.method.checkpoint(self.model),
            model=self.model,
            opt=self.opt,
            progress=progress,
            extra=extra,
        )
