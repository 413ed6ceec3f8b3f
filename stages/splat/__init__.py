"""Stage `splat`: a trained run -> 3-D Gaussian splats optimised against the training photos (INRIA PLY or .splat).

    nerfpipe splat RUN_DIR OUT.ply [--max-seconds 300] [--format auto|ply|splat] [--frame upright|user|normalized]

Steps:
1. Initialisation from the field ("NeRF to splats", `model.splat_init.gaussians_from_field`): Gaussians where
   training rays end on one surface, coloured by the field, sized by their neighbours (its doc has the rule and
   what it measured).
2. Optimisation on the shared training loop (`model.loop`: budget, clock, non-finite recovery): each step renders one
   random training view whole and takes an Adam step on the L1 error against its photo (photos with alpha are
   put on the run's background, as the field was evaluated); learning rates are 3DGS's (means scaled by the scene's
   extent), decaying x LR_DECAY over the run. Colours are spherical harmonics up to `--sh-degree` (3), one band
   added at each of SH_AT (the higher bands at SH_REST_LR of the colour's rate: 1 on a CPU budget). With
   `--densify` (off by default: `Config.densify` says why), `model.splat_density` clones, splits and prunes every
   DENSIFY_EVERY steps while the run is in DENSIFY_SPAN.
3. Export (`stages.splat.files`): Gaussians with opacity below 1/255 are dropped (invisible); the rest go to the
   output frame (`data.export_frame`), the SH bands turned with it: `upright` (default) the user's frame turned so
   that the scene's up is -Y, the 3DGS files' convention that splat viewers are built for (COLMAP's y points down);
   `user` the source frame as it came in; `normalized` the scene frame; in INRIA's PLY layout or the `.splat`
   layout (`data.splat_ply`). OUT.report.json next to it holds `out_from_scene` and `out_from_source` (4x4), the
   figures and the self-check; OUT.metrics.csv the step, seconds, loss and PSNR of each step's view (training
   seconds: the evaluation before and after is left out of the budget).

Backends (`backend`, decided once: `model.splat_backends`): gsplat's CUDA rasteriser when the device is CUDA and
`import gsplat` works, else `radiance.splats` (any device; on CPU its compositing runs in the numba kernels of
`radiance.splat_cpu`, elsewhere in torch); the report records which and why (`backend`, `backend_why`, `kernel`).
Self-check (report `check`): `psnr_gain`, the mean PSNR on EVAL_VIEWS training views after the optimisation less
before it (>= 0), and `non_finite` parameters (0). Held-out views are scored by `nerfpipe eval OUT.ply`.

Modules: `steps` (the optimisation's settings and step), `files` (the Gaussians as the files store them).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.checks import Check, verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.export_frame import check_frame_options, export_frame
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, config_to_json, sidecar, write_manifest
from nerfpipe.data.splat_ply import write_ply, write_splat
from nerfpipe.model import load_trained, resolve_device
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingLoop
from nerfpipe.model.run import require
from nerfpipe.model.splat_backends import choose_backend, kernel_name
from nerfpipe.model.splat_init import gaussians_from_field
from nerfpipe.model.splat_views import load_training_photos
from nerfpipe.radiance import splats as sp
from nerfpipe.stages.splat.files import to_file as _to_file
from nerfpipe.stages.splat.steps import (
    DENSIFY_LIMIT,
    DENSIFY_OFF,
    EVAL_VIEWS,
    LR_DECAY,
    LRS,
    SH_AT,
    SH_REST_LR,
    Steps,
    colour_left_out,
    densification,
    extent_of,
    score,
    shown_splats,
)

__all__ = ["Config", "Outputs", "run", "VERSION", "DENSIFY_OFF"]

VERSION = "2"


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory (config.json + checkpoint.pt from `train`)."""
    out: Path
    """Output file, .ply (INRIA's layout) or .splat; OUT.report.json and OUT.metrics.csv go next to it."""
    format: Literal["auto", "ply", "splat"] = "auto"
    """auto (from the extension) | ply | splat."""
    max_seconds: float = 300.0
    """Optimisation budget in seconds (the initialisation and the evaluation are not counted)."""
    max_steps: int = 30_000
    """Optimisation budget in steps (one training view each)."""
    gaussians: int = 50_000
    """Gaussians initialised from the field (fewer when too few training rays hit a surface); densification adds
    more. 50k: within a CPU budget fewer Gaussians take more steps, and on the fox and lego_400 (300 s) 50k scored
    best of 25k-300k (docs/SPLATS.md)."""
    frame: Literal["upright", "user", "normalized"] = "upright"
    """Output frame: upright (the user's frame turned so that the scene's up is -Y, the 3DGS files' convention that
    splat viewers open upright, the scene's centre at the origin they orbit; `data.export_frame`) | user (the source
    frame before convert, as it came in) | normalized (the scene frame)."""
    up: tuple[float, float, float] | None = None
    """With frame "upright": the scene's up as a direction x,y,z in the user's frame; None: the scene frame's +z
    (convert's choice: the cameras' mean up for COLMAP and LLFF worlds)."""
    downscale: float | None = None
    """Optimise at 1/downscale of the photos (None: the factor the run trained at)."""
    backend: Literal["auto", "torch", "gsplat"] = "auto"
    """Rasteriser: auto (gsplat on CUDA when installed, else torch) | torch | gsplat."""
    densify: bool = False
    """Clone, split and prune Gaussians during the optimisation (3DGS's adaptive density control,
    `model.splat_density`), up to DENSIFY_LIMIT x the initial count. Off by default: in 300 s on CPU at 50k
    Gaussians it measured +0.13 dB on the fox and -0.20 dB on lego_400 (noise ~0.3 dB), the steps it costs
    against the detail it adds."""
    sh_degree: int = 3
    """Spherical-harmonics degree of the colours (0: one colour a Gaussian; 1..3: view-dependent), raised one band at
    a time over the run (SH_AT). 3 against 0, 300 s on CPU: lego_400 33.05 against 31.47 dB, the fox 30.99 against
    28.77 dB held-out (docs/SPLATS.md, "View-dependent colour")."""
    seed: int = 0
    """Seed of the initial rays, the view order and the split Gaussians' centres."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out: Path
    report: Path
    metrics: Path
    gaussians: int
    steps: int
    seconds: float
    psnr_init: float
    psnr_final: float
    backend: str


# ---------------------------------------------------------------------------------------------- optimisation
def _out_format(config: Config) -> str:
    suffix = Path(config.out).suffix.lower()
    fmt = {".ply": "ply", ".splat": "splat"}.get(suffix) if config.format == "auto" else config.format
    if fmt is None or fmt not in ("ply", "splat"):
        raise UserError(f"{config.out}: unknown splat format; expected a .ply or .splat file (or format ply|splat)")
    return fmt


def _validate(config: Config) -> str:
    if not config.max_seconds > 0:
        raise UserError(f"max_seconds: expected > 0, got {config.max_seconds}")
    if config.max_steps < 0:
        raise UserError(f"max_steps: expected >= 0, got {config.max_steps}")
    if config.gaussians < 4:
        raise UserError(f"gaussians: expected at least 4, got {config.gaussians}")
    if config.sh_degree not in (0, 1, 2, 3):
        raise UserError(f"sh_degree: expected 0, 1, 2 or 3, got {config.sh_degree}")
    if config.downscale is not None and not config.downscale > 0:
        raise UserError(f"downscale: expected > 0, got {config.downscale}")
    check_frame_options(config.frame, config.up)
    return _out_format(config)


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Splats from RUN_DIR (module doc)."""
    started = time.time()
    fmt = _validate(config)
    out = Path(config.out)
    device = resolve_device(config.device)
    backend = choose_backend(config.backend, device)
    trained = load_trained(config.run_dir, device)
    require(trained, "rays", stage="splat")  # Gaussians are placed where training rays end
    scene = trained.scene
    train_idx = scene.split("train")
    downscale = config.downscale or trained.downscale
    background = trained.background.detach().float().cpu().reshape(3)
    views = load_training_photos(scene, train_idx, downscale, background.numpy())
    gen = torch.Generator().manual_seed(config.seed)
    splats, init = gaussians_from_field(trained, views.intrinsics, views.world_from_cams, config.gaussians, gen)
    rest = splats.sh.new_zeros(len(splats), (config.sh_degree + 1) ** 2 - 1, 3)  # higher bands start at 0
    splats = sp.Splats(*splats.parameters()[:4], sh=torch.cat([splats.sh, rest], dim=1))
    splats = sp.Splats(*(p.to(device).requires_grad_(True) for p in splats.parameters()))
    bg = background.to(device)
    picks = sorted({int(i) for i in np.linspace(0, len(train_idx) - 1, min(EVAL_VIEWS, len(train_idx))).round()})
    psnr_init = score(splats, views, backend, bg, picks)

    extent = extent_of(views)
    scales = {**LRS, "means": LRS["means"] * extent}
    opt = torch.optim.Adam(
        [
            {"params": [p], "lr": scales[name], "lr_scale": scales[name]}
            for name, p in zip(LRS, splats.parameters(), strict=True)
        ],
        eps=1e-15,
    )
    metrics = MetricsLog(sidecar(out, "metrics.csv"), ["step", "seconds", "loss", "psnr"])
    progress = progress or NO_PROGRESS
    clock, task = Clock(), progress.add_task("splat", total=config.max_steps)
    limit = int(DENSIFY_LIMIT * len(splats))
    steps = Steps(
        splats=splats,
        opt=opt,
        views=views,
        backend=backend,
        background=bg,
        gen=gen,
        clock=clock,
        metrics=metrics,
        progress=progress,
        task=task,
        extent=extent,
        limit=limit,
        densify=config.densify,
        sh_degree=config.sh_degree,
    )
    settings = LoopSettings(
        name="splat",
        budget=Budget(max_steps=config.max_steps, max_seconds=config.max_seconds),
        schedule=Schedule(lr=1.0, decay=LR_DECAY),
    )
    seconds = TrainingLoop(settings, steps, clock).run() if config.max_steps > 0 else 0.0
    splats = steps.splats
    psnr_final = score(splats, views, backend, bg, picks)

    final = sp.Splats(*(p.detach().cpu().double() for p in shown_splats(splats).parameters()))
    non_finite = int(sum((~torch.isfinite(p)).sum() for p in final.parameters()))
    out_from_scene, frame_info = export_frame(scene.source_from_scene(), config.frame, "splat", config.up)
    data, dropped = _to_file(final, out_from_scene)
    checks = [
        Check.lower(
            "psnr_gain",
            psnr_final - psnr_init,
            0.0,
            "the optimisation made the splats worse than their "
            "initialisation on the training views: a learning rate too high, or the wrong photos",
            "dB",
        ),
        Check.upper("non_finite", non_finite, 0, "NaN or inf in the Gaussians' parameters: the optimisation diverged"),
    ]
    # OUT takes its name only after its report is written: a failure in between leaves no OUT that looks done
    with atomic_path(out) as tmp:
        (write_ply if fmt == "ply" else write_splat)(tmp, data)
        metrics.save()
        report = write_manifest(
            out.parent,
            name=sidecar(out, "report.json").name,
            stage="splat",
            started=started,
            version=VERSION,
            inputs=[Path(config.run_dir) / "checkpoint.pt", Path(config.run_dir) / "config.json"],
            outputs=[out, metrics.path],
            used={
                "backend": backend.name,
                "backend_why": backend.why,
                "kernel": kernel_name(backend, device),
                "device": str(device),
                "format": fmt,
                "init": init,
                "densification": densification(steps, config.densify),
                "views": len(train_idx),
                "downscale": downscale,
                "scored_views": picks,
                "loss": "L1 on one whole training view per step",
                "sh": {
                    "degree": config.sh_degree,
                    "raised_at": list(SH_AT[: config.sh_degree]),
                    "rest_lr": f"{SH_REST_LR:g} x the colour's",
                },
                "learning_rates": scales,
                "lr_decay": LR_DECAY,
                "scene_extent": extent,
                "background": background.tolist(),
                "dropped_invisible": dropped,
                "camera_model": "pinhole (distortion coefficients are not applied)",
            },
            left_out={
                **({} if config.densify else {"densification": DENSIFY_OFF}),
                **colour_left_out(config.sh_degree, fmt),
                "ssim_loss": "L1 only (3DGS adds 0.2 D-SSIM)",
                "held_out_score": "test views are not scored here (nerfpipe eval OUT.ply scores them)",
            },
            **frame_info,
            out_from_scene=out_from_scene.tolist(),
            gaussians=len(data),
            steps=steps.step,
            seconds=round(seconds, 3),
            psnr_train_init=round(psnr_init, 4),
            psnr_train_final=round(psnr_final, 4),
            config=config_to_json(config),
            **verdict(checks),
        )
    return Outputs(
        out=out,
        report=report,
        metrics=metrics.path,
        gaussians=len(data),
        steps=steps.step,
        seconds=seconds,
        psnr_init=psnr_init,
        psnr_final=psnr_final,
        backend=backend.name,
    )
