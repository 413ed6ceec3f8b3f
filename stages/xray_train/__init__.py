"""Stage `xray-train`: fit an attenuation field to X-ray projections (a projection scene) -> an X-ray run.

    nerfpipe xray-train SCENE RUN_DIR [--field grid|tensorf] [--max-seconds 600] [--tv 0.0] [--threads N] [--resume]

SCENE: a projection scene folder (`xray-simulate`), a NAF / SAX-NeRF `*.pickle`, or an R2-Gaussian folder
(data.projections.read_any). A pickle is read by the restricted unpickler (data.safe_pickle: plain data and
numpy arrays; any other global is refused and nothing from the file runs) unless `--trust-pickle`. The field
is density-only (attenuation mu per length unit, no colour, no view direction) over the scene grid's box:
"grid" (radiance.fields.voxel.VoxelField, trilinear, the CPU default) or "tensorf" (TensoRF VM,
has_color=False). Rendering: Beer-Lambert through the compositing core
(radiance.render.render_attenuation); loss on line integrals -log(I / I0) (stages.xray_train.loop).

Error against run time, as for photos (metrics.csv, psnr_vs_time.png): train projection PSNR per logged step;
every `eval_every` training seconds the field is sampled on the scene grid and scored: held-out projection
PSNR (the test views re-projected through that volume with the exact voxel projector) and, when the ground
truth is known, 3-D PSNR / SSIM (radiance.ct_metrics). Evaluation pauses the clock.

The loop is the one `train` runs (`model.loop.TrainingLoop`; the step is `stages.xray_train.loop.XraySteps`):
the budget, the learning-rate decay, checkpoints every `checkpoint_seconds` and at the end, Ctrl-C or SIGTERM
(a checkpoint at the current step, then one line and exit 130/143; continue with `--resume`), and recovery from a
non-finite loss (the last good state at half the learning rate; the third time the run stops).

Run directory (model.xray): config.json, checkpoint.pt, metrics.csv, psnr_vs_time.png, volume.npy (mu on the
scene grid, float32, 1 / length unit), manifest.json (last; says what was used and what was left out and why).
A folder holding a run (checkpoint.pt or manifest.json) is refused unless `--resume` (continue it: the step, the
training seconds, the learning-rate factor, the schedule and the random state go on from the checkpoint; the
manifest is removed until the run ends again) or `--overwrite`.
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from nerfpipe.data.atomic import write_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.projections import ProjectionScene, read_any
from nerfpipe.data.rundir import MetricsLog, config_to_json, output_folder, scene_from_run, write_manifest
from nerfpipe.data.safe_pickle import PickleRefused
from nerfpipe.data.stop import stop_on_signals
from nerfpipe.data.volumes import write_npy
from nerfpipe.model.device import cpu_threads, resolve_device
from nerfpipe.model.loop import TrainingLoop
from nerfpipe.model.xray import XRAY_FIELDS
from nerfpipe.stages.xray_train.loop import XraySteps, evaluate
from nerfpipe.stages.xray_train.report import plot_metrics
from nerfpipe.stages.xray_train.setup import start

__all__ = ["Config", "Outputs", "run"]

VERSION = "1"
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
    the line integral is unbiased; docs/MEASUREMENTS.md, "X-ray")."""
    resolution: tuple[int, int] | None = None
    """Voxels along the longest axis at the start and at the end (None: a quarter of the scene grid's, then
    all of it); upsampled at `upsample_at`."""
    upsample_at: tuple[float, ...] = (0.1, 0.25)
    """Run-progress fractions at which the field is upsampled (geometric steps to the final resolution)."""
    lr: float | None = None
    """Learning rate (None: Adam 0.02, in units of twice the scan's mean attenuation for grid; sart: 0.5;
    docs/MEASUREMENTS.md, "X-ray")."""
    lr_decay: float = 0.1
    """Final learning-rate factor (exponential decay over the run)."""
    optimizer: Literal["adam", "sart"] = "adam"
    """adam: Adam on the loss. sart (grid field only): the same loss with SART's per-ray and per-voxel
    normalisation (ordered-subsets SART over random ray batches); `lr` is then its relaxation factor."""
    tv: float = 0.0
    """grid: weight of the total-variation prior (mean |neighbour difference| of the grid; it is taken over the
    whole grid each step: docs/MEASUREMENTS.md, "X-ray")."""
    rank: int = 16
    """tensorf: VM components per axis."""
    eval_every: float = 30.0
    """Score the volume every this many training seconds (0: only at the end)."""
    eval_test_views: int = 4
    """Held-out views re-projected at each periodic evaluation (all of them at the end)."""
    log_every: int = 25
    """Write a metrics row every this many steps."""
    checkpoint_seconds: float = 60.0
    """Write checkpoint.pt every this many seconds of wall-clock time, so a killed run loses at most that (0: only
    at the end and on Ctrl-C or SIGTERM)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """"auto": CUDA when available, else CPU."""
    seed: int = 0
    """Seed for initialisation and ray batches."""
    threads: int | None = None
    """CPU: torch intra-op threads (None: torch's default)."""
    overwrite: bool = False
    """Replace an earlier output in run_dir (set aside in RUN_DIR.previous/ until this one is written)."""
    resume: bool = False
    """Continue from run_dir/checkpoint.pt (an interrupted run, or a finished one with a larger budget): the step
    count, training seconds, optimiser state and random state continue."""
    trust_pickle: bool = False
    """Unpickle a NAF *.pickle scene with the plain unpickler, which runs any code the file names: only for a
    file you trust. Off: the restricted reader (data.safe_pickle), which loads plain data and numpy arrays and
    refuses anything else. Later stages reading this run's scene never trust it."""


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
    if config.optimizer == "sart" and not XRAY_FIELDS[config.field].linear:
        raise UserError(f"optimizer: sart needs the grid field (linear in its voxels), got field {config.field!r}")
    if config.threads is not None and config.threads < 1:
        raise UserError(f"threads: expected >= 1, got {config.threads}")
    if not config.checkpoint_seconds >= 0:
        raise UserError(f"checkpoint_seconds: expected >= 0, got {config.checkpoint_seconds}")
    if config.resume and config.overwrite:
        raise UserError("pass either --resume (continue the run) or --overwrite (replace it), not both")


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """See the module doc; torch's CPU threads are set to config.threads for the call and restored after."""
    _validate(config)
    marks = ("checkpoint.pt", "manifest.json")
    with output_folder(config.run_dir, overwrite=config.overwrite, resume=config.resume, marks=marks):
        with cpu_threads(config.threads):
            return _run(config, progress or NO_PROGRESS)


def _run(config: Config, progress: Progress) -> Outputs:
    started = time.time()
    steps = _setup(config, progress)
    resumed_from = (steps.step, steps.clock.before)
    with stop_on_signals() as stop:
        seconds = TrainingLoop(steps.settings(), steps, steps.clock, stop).run()
    scene, run_dir = steps.scene, Path(config.run_dir)
    final = evaluate(steps.model, scene, list(scene.split("test")))
    steps.metrics.append(
        step=steps.step,
        seconds=round(seconds, 3),
        resolution=steps.schedule[steps.level],
        lr=steps.lr,
        **{k: round(v, 4) for k, v in final.items() if k != "volume"},
    )
    volume_path = write_npy(run_dir / "volume.npy", final["volume"].numpy().astype(np.float32))
    metrics = steps.metrics.save()
    plot = plot_metrics(steps.metrics.rows, run_dir / "psnr_vs_time.png")
    used = _used(steps, seconds, final)
    if config.resume:
        used["resumed_from"] = {"step": resumed_from[0], "seconds": round(resumed_from[1], 2)}
    manifest = write_manifest(
        run_dir,
        stage="xray-train",
        started=started,
        version=VERSION,
        inputs=[Path(config.scene) / "projections.json" if Path(config.scene).is_dir() else config.scene],
        outputs=[steps.ckpt_path, volume_path, metrics, plot],
        used=used,
        left_out=_left_out(scene),
    )
    return Outputs(
        run_dir=run_dir,
        checkpoint=steps.ckpt_path,
        volume=volume_path,
        metrics=metrics,
        plot=plot,
        manifest=manifest,
        steps=steps.step,
        seconds=seconds,
        psnr_3d=final.get("psnr_3d"),
        ssim_3d=final.get("ssim_3d"),
        test_proj_psnr=final.get("test_proj_psnr"),
    )


def _setup(config: Config, progress: Progress) -> XraySteps:
    """Read the scene, build the field (or read it back with --resume), write config.json; the run's step."""
    device = resolve_device(config.device)
    try:
        scene = read_any(config.scene, trust_pickle=config.trust_pickle)
    except PickleRefused as exc:
        raise UserError(f"{exc}; if you trust this file, set trust_pickle=True") from None
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    begin = start(config, scene, device, gen)
    run_dir = Path(config.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "manifest.json").unlink(missing_ok=True)  # resumed: not a finished run until the end
    scene_abs = Path(config.scene).resolve()
    cfg_json = {
        **config_to_json(config),
        "scene": str(config.scene),
        "scene_abs": str(scene_abs),
        "scene_from_run": scene_from_run(run_dir, scene_abs),
    }
    write_json(run_dir / "config.json", cfg_json)
    metrics = MetricsLog(run_dir / "metrics.csv", METRICS)
    if config.resume:
        metrics.load()
        metrics.rows = [r for r in metrics.rows if int(r["step"]) <= begin.step]
    return XraySteps(
        config=config, scene=scene, begin=begin, gen=gen, device=device, metrics=metrics, progress=progress
    )


def _used(steps: XraySteps, seconds: float, final: dict) -> dict:
    config, scene = steps.config, steps.scene
    used = {
        "field": steps.model.config(),
        "renderer": "radiance.render.render_attenuation (Beer-Lambert, compositing core)",
        "loss": "mean squared error of line integrals -log(I/I0)" + (f" + {config.tv} * TV" if config.tv else ""),
        "samples_per_ray": steps.samples,
        "mu_ref": steps.mu_ref,
        "resolution_schedule": steps.schedule,
        "train_views": len(scene.split("train")),
        "test_views": len(scene.split("test")),
        "steps": steps.step,
        "seconds": round(seconds, 2),
        "device": str(steps.device),
        "threads": torch.get_num_threads(),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "final": {k: v for k, v in final.items() if k != "volume"},
        "noise": scene.noise,
    }
    if steps.lr_factor != 1.0:
        used["lr_factor"] = steps.lr_factor  # non-finite losses halved the learning rate (model.loop)
    return used


def _left_out(scene: ProjectionScene) -> dict:
    return {
        "colour": "X-ray detectors measure one attenuated intensity per pixel: the field is density only",
        "view direction": "attenuation mu(x) is isotropic: no view-dependent term",
        "background": "Beer-Lambert has no emission, so nothing is composited over a background",
        "occupancy grid / empty-space skipping": "every sample inside the box counts towards the line integral",
        **({} if scene.volume is not None else {"3-D PSNR/SSIM": "the scene has no ground-truth volume"}),
        **({} if scene.split("test") else {"held-out projection PSNR": "the scene has no test split"}),
    }
