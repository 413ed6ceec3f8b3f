"""Stage `xray-train`: fit an attenuation field to X-ray projections (a projection scene) -> an X-ray run.

    nerfpipe xray-train SCENE RUN_DIR [--field grid|tensorf] [--max-seconds 600] [--tv 0.0] [--threads N]

SCENE: a projection scene folder (`xray-simulate`), a NAF / SAX-NeRF `*.pickle`, or an R2-Gaussian folder
(data.projections.read_any). The field is density-only (attenuation mu per length unit, no colour, no view
direction) over the scene grid's box: "grid" (radiance.fields.voxel.VoxelField, trilinear, the CPU default) or
"tensorf" (TensoRF VM, has_color=False). Rendering: Beer-Lambert through the compositing core
(radiance.render.render_attenuation); loss on line integrals -log(I / I0) (stages.xray_train.loop).

Error against run time, as for photos (metrics.csv, psnr_vs_time.png): train projection PSNR per logged step;
every `eval_every` training seconds the field is sampled on the scene grid and scored: held-out projection
PSNR (the test views re-projected through that volume with the exact voxel projector) and, when the ground
truth is known, 3-D PSNR / SSIM (radiance.ct_metrics). Evaluation pauses the clock.

Run directory (model.xray): config.json, checkpoint.pt, metrics.csv, psnr_vs_time.png, volume.npy (mu on the
scene grid, float32, 1 / length unit), manifest.json (last; says what was used and what was left out and why).
"""

from __future__ import annotations

import math
import resource
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from data.atomic import write_json
from data.errors import UserError
from data.progress import NO_PROGRESS, Progress
from data.projections import ProjectionScene, read_any
from data.rundir import MetricsLog, config_to_json, output_folder, write_manifest
from data.volumes import write_npy
from model.device import cpu_threads, resolve_device
from model.xray import (
    attenuation_field,
    field_line_integrals,
    field_volume,
    grid_shape_at,
    samples_for,
    save_xray_checkpoint,
)
from radiance.aabb import ray_aabb_intersect
from radiance.ct_metrics import data_range, psnr_3d, psnr_projections, ssim_3d
from radiance.metrics import psnr_from_mse
from radiance.xray import detector_rays, rays_for_pixels, siddon_project
from stages.xray_train.loop import Batches, Clock, LoopState, make_optimizer, sart_step, set_lr, train_step
from stages.xray_train.report import plot_metrics

__all__ = ["Config", "Outputs", "run"]

VERSION = "1"
DEFAULT_LR = {("adam", "grid"): 0.02, ("adam", "tensorf"): 0.02, ("sart", "grid"): 0.5}
METRICS = ["step", "seconds", "loss", "train_psnr", "test_proj_psnr", "psnr_3d", "ssim_3d", "lr", "resolution"]


@dataclass(frozen=True, kw_only=True)
class Config:
    scene: Path
    """Projection scene: folder with projections.json, a NAF *.pickle, or an R2-Gaussian folder."""
    run_dir: Path
    """Output run directory (created)."""
    field: Literal["grid", "tensorf"] = "grid"
    """Field: "grid" (dense trilinear voxel grid, the fast one on a CPU) or "tensorf" (TensoRF VM)."""
    max_seconds: float = 600.0
    """Stop after this many seconds of training (evaluation excluded)."""
    max_steps: int = 1_000_000
    """Stop after this many optimizer steps."""
    batch_rays: int = 1024
    """Rays per optimizer step."""
    step_ratio: float = 2.0
    """Samples along each ray: the box diagonal cut every `step_ratio` voxels of the current grid (jittered, so
    the line integral is unbiased). Thorax 128^3, 50 views, 2000 steps: 1.0 -> 25.91 dB in 245 s, 2.0 -> 25.78 dB
    in 77 s."""
    resolution: tuple[int, int] | None = None
    """Voxels along the longest axis at the start and at the end (None: a quarter of the scene grid's, then
    all of it); upsampled at `upsample_at`."""
    upsample_at: tuple[float, ...] = (0.1, 0.25)
    """Run-progress fractions at which the field is upsampled (geometric steps to the final resolution)."""
    lr: float | None = None
    """Learning rate (None: Adam 0.02, in units of twice the scan's mean attenuation for grid; sart: 0.5).
    Thorax 128^3, 50 views, 2000 steps: 0.02 -> 25.91 dB (SSIM 0.810), 0.04 -> 26.05 (0.784), 0.1 (1500 steps)
    -> 22.6; short runs want more (24^3 phantom, 300 steps: 0.02 -> 22.8 dB, 0.1 -> 31.6)."""
    lr_decay: float = 0.1
    """Final learning-rate factor (exponential decay over the run)."""
    optimizer: Literal["adam", "sart"] = "adam"
    """adam: Adam on the loss. sart (grid field only): the same loss with SART's per-ray and per-voxel
    normalisation (ordered-subsets SART over random ray batches); `lr` is then its relaxation factor."""
    tv: float = 0.0
    """grid: weight of the total-variation prior (mean |neighbour difference| of the grid). Thorax, 50 views,
    2000 steps: 0.1 -> SSIM 0.804 -> 0.858 but PSNR 25.78 -> 25.34 dB and 3.7x the time per step (the prior is
    taken over the whole grid each step); 1e-4 changes nothing."""
    rank: int = 16
    """tensorf: VM components per axis."""
    eval_every: float = 30.0
    """Score the volume every this many training seconds (0: only at the end)."""
    eval_test_views: int = 4
    """Held-out views re-projected at each periodic evaluation (all of them at the end)."""
    log_every: int = 25
    """Write a metrics row every this many steps."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """"auto": CUDA when available, else CPU."""
    seed: int = 0
    """Seed for initialisation and ray batches."""
    threads: int | None = None
    """CPU: torch intra-op threads (None: torch's default)."""
    overwrite: bool = False
    """Replace an earlier output in run_dir (set aside in RUN_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    run_dir: Path
    checkpoint: Path
    volume: Path
    metrics: Path
    plot: Path
    manifest: Path
    steps: int
    seconds: float
    psnr_3d: float | None
    ssim_3d: float | None
    test_proj_psnr: float | None


def _validate(config: Config) -> None:
    if not config.max_seconds > 0 or config.max_steps < 1:
        raise UserError(f"max_seconds, max_steps: expected > 0, got {config.max_seconds}, {config.max_steps}")
    if config.batch_rays < 1:
        raise UserError(f"batch_rays: expected >= 1, got {config.batch_rays}")
    if not config.step_ratio > 0:
        raise UserError(f"step_ratio: expected > 0, got {config.step_ratio}")
    if config.lr is not None and not config.lr > 0:
        raise UserError(f"lr: expected > 0, got {config.lr}")
    if config.tv < 0:
        raise UserError(f"tv: expected >= 0, got {config.tv}")
    if config.resolution is not None and min(config.resolution) < 2:
        raise UserError(f"resolution: expected >= 2 voxels, got {config.resolution}")
    if config.optimizer == "sart" and config.field != "grid":
        raise UserError(f"optimizer: sart needs the grid field (linear in its voxels), got field {config.field!r}")
    if config.threads is not None and config.threads < 1:
        raise UserError(f"threads: expected >= 1, got {config.threads}")


def _mu_ref(scene: ProjectionScene, gen: torch.Generator, n: int = 65536) -> float:
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


def _schedule(config: Config, grid_longest: int) -> list[int]:
    start, end = config.resolution or (max(2, grid_longest // 4), grid_longest)
    k = len(config.upsample_at)
    return [round(math.exp(math.log(start) + (math.log(end) - math.log(start)) * i / k)) for i in range(k + 1)]


@torch.no_grad()
def _evaluate(model, scene: ProjectionScene, test_views: list[int]) -> dict:
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


def _evenly(ids: tuple[int, ...], k: int) -> list[int]:
    if k <= 0 or not ids:
        return []
    if k >= len(ids):
        return list(ids)
    return [ids[int(i)] for i in np.linspace(0, len(ids) - 1, k).round()]


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """See the module doc; torch's CPU threads are set to config.threads for the call and restored after."""
    with output_folder(config.run_dir, overwrite=config.overwrite):
        with cpu_threads(config.threads):
            return _run(config, progress)


def _run(config: Config, progress: Progress | None) -> Outputs:
    started = time.time()
    progress = progress or NO_PROGRESS
    _validate(config)
    device = resolve_device(config.device)
    scene = read_any(config.scene)
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    mu_ref = _mu_ref(scene, gen)
    schedule = _schedule(config, max(scene.grid.shape))
    lr = config.lr if config.lr is not None else DEFAULT_LR[config.optimizer, config.field]
    model = attenuation_field(
        scene.grid, kind=config.field, resolution=schedule[0], rank=config.rank, mu_ref=mu_ref
    ).to(device)
    opt = make_optimizer(model, lr)

    def samples_at(level: int) -> int:  # the step follows the current voxel size (coarse grids: fewer samples)
        coarse = scene.grid.shape[0] * scene.grid.spacing[0] / grid_shape_at(scene.grid, schedule[level])[0]
        return samples_for(scene.grid, config.step_ratio * coarse / scene.grid.spacing[0])

    n_samples = samples_at(0)
    box = torch.as_tensor(scene.grid.box, dtype=torch.float32, device=device)
    batches = Batches(
        geometry=scene.geometry,
        projections=torch.from_numpy(scene.projections).reshape(scene.geometry.n_views, -1),
        train_views=torch.as_tensor(scene.split("train")),
        generator=gen,
    )
    p_range = data_range(scene.projections[list(scene.split("train"))])
    test_all = list(scene.split("test"))
    test_periodic = _evenly(tuple(test_all), config.eval_test_views)

    def unit_integrals(o, d):  # line integrals of theta = 1 (mu = mu_ref) over the box: SART's row sums
        t0, t1, hit = ray_aabb_intersect(o, d, box)
        return torch.where(hit, (t1 - t0) * mu_ref, torch.zeros_like(t0))

    def render(o, d):
        return field_line_integrals(model, o, d, box, n_samples, jitter=True, generator=gen)

    run_dir = Path(config.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg_json = {**config_to_json(config), "scene": str(config.scene), "scene_abs": str(Path(config.scene).resolve())}
    write_json(run_dir / "config.json", cfg_json)
    log = MetricsLog(run_dir / "metrics.csv", METRICS)
    state = LoopState()
    clock = Clock()
    next_eval = config.eval_every if config.eval_every > 0 else math.inf
    upsample_at = list(config.upsample_at)
    level = 0
    task = progress.add_task("xray-train", total=config.max_seconds)
    recent: list[float] = []
    cur_lr = lr
    while state.step < config.max_steps and clock() < config.max_seconds:
        frac = max(state.step / config.max_steps, clock() / config.max_seconds)
        while level < len(upsample_at) and frac >= upsample_at[level]:
            level += 1
            if config.field == "grid":
                model.upsample(grid_shape_at(scene.grid, schedule[level]))
            else:
                model.upsample(schedule[level])
            opt = make_optimizer(model, lr)
            n_samples = samples_at(level)
        cur_lr = lr * config.lr_decay**frac
        set_lr(opt, cur_lr)
        batch = batches.draw(config.batch_rays, device)
        if config.optimizer == "sart":
            data_loss = loss = sart_step(model, batch, render, unit_integrals, cur_lr)
        else:
            data_loss, loss = train_step(model, opt, batch, render, config.tv)
        if not math.isfinite(loss):
            raise RuntimeError(f"training diverged at step {state.step} (loss {loss})")
        state.step += 1
        recent.append(data_loss)
        if state.step % config.log_every == 0 or clock() >= next_eval:
            row = {
                "step": state.step,
                "seconds": round(clock(), 3),
                "loss": float(np.mean(recent)),
                "train_psnr": round(psnr_from_mse(float(np.mean(recent)) / p_range**2), 3),
                "lr": cur_lr,
                "resolution": schedule[level],
            }
            recent = []
            if clock() >= next_eval:
                clock.pause()
                ev = _evaluate(model, scene, test_periodic)
                row.update({k: round(v, 4) for k, v in ev.items() if k != "volume"})
                next_eval += config.eval_every
                clock.resume()
            log.append(**row)
            if "psnr_3d" in row or "test_proj_psnr" in row:
                log.save()  # the curve so far is on disk while a long run goes on
            progress.update(task, completed=min(clock(), config.max_seconds))
    seconds = clock()
    clock.pause()

    final = _evaluate(model, scene, test_all)
    log.append(
        step=state.step,
        seconds=round(seconds, 3),
        resolution=schedule[level],
        lr=cur_lr,
        **{k: round(v, 4) for k, v in final.items() if k != "volume"},
    )
    volume_path = write_npy(run_dir / "volume.npy", final["volume"].numpy().astype(np.float32))
    ckpt = run_dir / "checkpoint.pt"
    save_xray_checkpoint(
        ckpt,
        model,
        opt,
        step=state.step,
        seconds=seconds,
        mu_ref=mu_ref,
        n_samples_render=samples_for(scene.grid, 0.5 * config.step_ratio),
    )
    metrics = log.save()
    plot = plot_metrics(log.rows, run_dir / "psnr_vs_time.png")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    manifest = write_manifest(
        run_dir,
        stage="xray-train",
        started=started,
        version=VERSION,
        inputs=[Path(config.scene) / "projections.json" if Path(config.scene).is_dir() else config.scene],
        outputs=[ckpt, volume_path, metrics, plot],
        used={
            "field": model.config(),
            "renderer": "radiance.render.render_attenuation (Beer-Lambert, compositing core)",
            "loss": "mean squared error of line integrals -log(I/I0)" + (f" + {config.tv} * TV" if config.tv else ""),
            "samples_per_ray": [samples_at(i) for i in range(len(schedule))],
            "mu_ref": mu_ref,
            "resolution_schedule": schedule,
            "train_views": len(scene.split("train")),
            "test_views": len(test_all),
            "steps": state.step,
            "seconds": round(seconds, 2),
            "device": str(device),
            "threads": torch.get_num_threads(),
            "peak_rss_mb": round(peak_mb, 1),
            "final": {k: v for k, v in final.items() if k != "volume"},
            "noise": scene.noise,
        },
        left_out={
            "colour": "X-ray detectors measure one attenuated intensity per pixel: the field is density only",
            "view direction": "attenuation mu(x) is isotropic: no view-dependent term",
            "background": "Beer-Lambert has no emission, so nothing is composited over a background",
            "occupancy grid / empty-space skipping": "every sample inside the box counts towards the line integral",
            **({} if scene.volume is not None else {"3-D PSNR/SSIM": "the scene has no ground-truth volume"}),
            **({} if test_all else {"held-out projection PSNR": "the scene has no test split"}),
        },
    )
    return Outputs(
        run_dir=run_dir,
        checkpoint=ckpt,
        volume=volume_path,
        metrics=metrics,
        plot=plot,
        manifest=manifest,
        steps=state.step,
        seconds=seconds,
        psnr_3d=final.get("psnr_3d"),
        ssim_3d=final.get("ssim_3d"),
        test_proj_psnr=final.get("test_proj_psnr"),
    )
