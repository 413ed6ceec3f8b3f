"""Stage `splat`: a trained run -> 3-D Gaussian splats optimised against the training photos (INRIA PLY or .splat).

    nerfpipe splat RUN_DIR OUT.ply [--max-seconds 300] [--format auto|ply|splat] [--frame user|normalized]

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
3. Export: Gaussians with opacity below 1/255 are dropped (invisible); the rest go to the output frame
   (`--frame user`: `scene.source_from_scene()`, the user's frame viewers expect, the SH bands turned with it;
   `normalized`: the scene frame),
   in INRIA's PLY layout or the `.splat` layout (`data.splat_ply`). OUT.report.json next to it holds
   `out_from_scene` (4x4), the figures and the self-check; OUT.metrics.csv the step, seconds, loss and PSNR of
   each step's view (training seconds: the evaluation before and after is left out of the budget).

Backends (`backend`, decided once: `model.splat_backends`): gsplat's CUDA rasteriser when the device is CUDA and
`import gsplat` works, else `radiance.splats` (any device; on CPU its compositing runs in the numba kernels of
`radiance.splat_cpu`, elsewhere in torch); the report records which and why (`backend`, `backend_why`, `kernel`).
Self-check (report `check`): `psnr_gain`, the mean PSNR on EVAL_VIEWS training views after the optimisation less
before it (>= 0), and `non_finite` parameters (0). Held-out views are scored by `nerfpipe eval OUT.ply`.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.checks import Check, verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, config_to_json, sidecar, write_manifest
from nerfpipe.data.splat_ply import SplatData, write_ply, write_splat
from nerfpipe.model import load_trained, resolve_device, splat_density
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingLoop
from nerfpipe.model.run import require
from nerfpipe.model.splat_backends import Backend, choose_backend, kernel_name
from nerfpipe.model.splat_init import gaussians_from_field
from nerfpipe.model.splat_views import TrainingPhotos, load_training_photos
from nerfpipe.radiance import splats as sp
from nerfpipe.radiance.metrics import psnr_from_mse

__all__ = ["Config", "Outputs", "run", "VERSION"]

VERSION = "1"
LRS = {"means": 1.6e-4, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh": 2.5e-3}
"""Adam learning rates per parameter (3DGS's; means' times the scene extent)."""
LR_DECAY = 0.1
SH_REST_LR = 1.0
"""The higher SH coefficients learn at this times the colour's rate. 3DGS uses 1/20 over 30k steps; our CPU budget
gives ~3k steps, and on lego_400 (300 s, field 33.78 dB) 1/20, 1/5, 1/2 and 1 scored 32.03, 32.58, 32.99 and 33.11
dB held-out: the bands need the full rate to settle in so few steps. The optimiser holds them divided by it (`_shown`
multiplies back), so one [N, K, 3] tensor keeps every coefficient of a Gaussian in its row (densification copies
rows) while Adam, whose step does not depend on the gradient's scale, moves them at that rate; a longer (GPU) budget
may want 3DGS's 1/20, unmeasured here."""
SH_AT = (0.1, 0.2, 0.3)
"""Run progress at which the colours' SH degree rises to 1, 2, 3 (3DGS: one band every 1000 of 30k steps, so that
the view-independent colour settles first); bands above `Config.sh_degree` are never used."""
DENSIFY_EVERY = 100
"""Steps between two densifications (3DGS)."""
DENSIFY_SPAN = (0.1, 0.6)
"""Densify while the run's progress (the larger of its step and time fractions) is in this span."""
DENSIFY_LIMIT = 2.0
"""Densification stops growing at this many times the initial Gaussians (each step's time grows with them)."""
DENSIFY_OFF = (
    "off by default (--densify): a fixed count; measured within noise in 300 s on CPU (fox +0.13 dB, "
    "lego_400 -0.20 dB at 50k Gaussians)"
)
"""What the report's left_out says when densification is off."""
EVAL_VIEWS = 8
"""Training views (evenly spaced) scored before and after the optimisation."""


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
    frame: Literal["user", "normalized"] = "user"
    """Output frame: user (the source frame before convert, what viewers expect) | normalized (the scene frame)."""
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
def _psnr(a: Tensor, b: Tensor) -> float:
    return psnr_from_mse(float(torch.mean((a.detach().float() - b.float()) ** 2)))


@dataclass(kw_only=True)
class _Steps:
    """The splat step on the shared loop (`model.loop.Stepper`; no checkpoints: the output is written at the end)."""

    splats: sp.Splats
    opt: torch.optim.Optimizer
    views: TrainingPhotos
    backend: Backend
    background: Tensor
    gen: torch.Generator
    clock: Clock
    metrics: MetricsLog
    progress: Progress
    task: Any
    extent: float
    limit: int
    """Most Gaussians densification may reach."""
    densify: bool
    sh_degree: int
    """The highest SH degree the run reaches (`Config.sh_degree`)."""
    step: int = 0
    lr_factor: float = 1.0
    degree: int = 0
    """The SH degree in use now (raised at SH_AT)."""
    last: dict = field(default_factory=dict)
    stats: splat_density.GradStats = field(init=False)
    refined_at: int = -1
    refinements: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.stats = splat_density.GradStats.zeros(len(self.splats), self.splats.means.device)

    def prepare(self, fraction: float) -> bool:
        """Densification (`model.splat_density.refine`) every DENSIFY_EVERY steps while the run's fraction is in
        DENSIFY_SPAN; True when the Gaussians were replaced. The SH degree in use follows the run's fraction (SH_AT)."""
        self.degree = min(self.sh_degree, sum(fraction >= f for f in SH_AT))
        if not (
            self.densify
            and self.step > 0
            and self.step % DENSIFY_EVERY == 0
            and self.step != self.refined_at
            and DENSIFY_SPAN[0] <= fraction < DENSIFY_SPAN[1]
        ):
            return False
        self.refined_at = self.step
        new, source, fresh, counts = splat_density.refine(
            self.splats, self.stats, extent=self.extent, limit=self.limit, gen=self.gen
        )
        self._replace([p.requires_grad_(True) for p in new.parameters()], source, fresh)
        self.refinements.append({"step": self.step, **counts})
        return True

    def _replace(self, params: list[Tensor], source: Tensor | None = None, fresh: Tensor | None = None) -> None:
        """New Gaussians in place of the current ones: the optimiser's moments follow `source` rows (densification),
        or are dropped (a restore loads its own)."""
        old = self.splats.parameters()
        if source is not None:
            splat_density.carry_adam(self.opt, old, params, source, fresh)
        else:
            splat_density.swap_parameters(self.opt, old, params)
        self.splats = sp.Splats(*params)
        self.stats = splat_density.GradStats.zeros(len(self.splats), params[0].device)

    def train_step(self, lr: float) -> bool:
        k = int(torch.randint(len(self.views.photos), (1,), generator=self.gen))
        device = self.splats.means.device
        target = self.views.target(k, device)
        intr = self.views.intrinsics[k]
        shown = _shown(self.splats, self.degree)
        rgb, means2d, visible = self.backend.render(shown, self.views.world_from_cams[k], intr, self.background)
        err = torch.mean(torch.abs(rgb - target))
        loss = float(err.detach())
        if not math.isfinite(loss):
            return False
        self.opt.zero_grad(set_to_none=True)
        err.backward()
        self.opt.step()
        if self.densify and means2d.grad is not None:
            self.stats.add(means2d.grad.reshape(-1, 2), visible, intr.w, intr.h)
        self.last = {"loss": loss, "psnr": _psnr(rgb, target)}
        return True

    def log(self, lr: float) -> None:
        self.metrics.append(
            step=self.step,
            seconds=round(self.clock(), 4),
            loss=round(self.last["loss"], 6),
            psnr=round(self.last["psnr"], 4),
        )
        self.progress.advance(self.task)

    def snapshot(self) -> tuple[list[Tensor], dict]:
        return [p.detach().clone() for p in self.splats.parameters()], copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[list[Tensor], dict]) -> None:
        """The snapshot's Gaussians (their count may differ from now's: densification) and optimiser state."""
        self._replace([p.clone().requires_grad_(True) for p in snapshot[0]])
        self.opt.load_state_dict(snapshot[1])

    def checkpoint(self, seconds: float) -> None:
        pass

    def finish(self, seconds: float) -> None:
        pass


def _shown(splats: sp.Splats, degree: int | None = None) -> sp.Splats:
    """The Gaussians the rasteriser sees: the optimiser's (SH_REST_LR: higher coefficients held / SH_REST_LR) with
    the SH bands up to `degree` (None: all it holds)."""
    k = splats.sh.shape[1] if degree is None else (degree + 1) ** 2
    scale = torch.full((k, 1), SH_REST_LR, dtype=splats.sh.dtype, device=splats.sh.device)
    scale[0] = 1.0
    return sp.Splats(splats.means, splats.log_scales, splats.quats, splats.opacity_logits, splats.sh[:, :k] * scale)


def _colour_left_out(sh_degree: int, fmt: str) -> dict[str, str]:
    """The report's `left_out` entry for view-dependent colour: none asked for, or a file layout that drops it."""
    if not sh_degree:
        return {"view_dependent_colour": "SH degree 0 (--sh-degree 0)"}
    if fmt == "splat":
        return {"view_dependent_colour": f"optimised to degree {sh_degree}; the .splat layout holds degree 0 only"}
    return {}


@torch.no_grad()
def _score(splats: sp.Splats, views: TrainingPhotos, backend: Backend, background: Tensor, picks: list[int]) -> float:
    device = splats.means.device
    shown = _shown(splats)
    return float(
        np.mean(
            [
                _psnr(
                    backend.render(shown, views.world_from_cams[k], views.intrinsics[k], background)[0],
                    views.target(k, device),
                )
                for k in picks
            ]
        )
    )


def _extent(views: TrainingPhotos) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera centre from their mean (1 for a single view)."""
    centres = torch.stack([p[:3, 3] for p in views.world_from_cams])
    radius = float(torch.linalg.norm(centres - centres.mean(0), dim=-1).max())
    return 1.1 * radius if radius > 0 else 1.0


# ---------------------------------------------------------------------------------------------- the stage
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
    return _out_format(config)


def _densification(steps: _Steps, config: Config) -> dict | str:
    if not config.densify:
        return "off (--densify turns it on)"
    d = splat_density
    return {
        "rule": f"every {DENSIFY_EVERY} steps while the run's progress is in {list(DENSIFY_SPAN)}: clone "
        f"(small) or split (largest scale > {d.PERCENT_DENSE} x extent) where the mean view-space "
        f"gradient > {d.GRAD_THRESHOLD}, prune opacity < {d.MIN_OPACITY}",
        "limit": steps.limit,
        "refinements": steps.refinements,
    }


def _to_file(splats: sp.Splats, out_from_scene: np.ndarray) -> tuple[SplatData, int]:
    """Visible Gaussians in the output frame, as the files store them; and how many were dropped."""
    keep = torch.sigmoid(splats.opacity_logits) >= sp.ALPHA_MIN
    moved = sp.transformed(splats.subset(keep), torch.as_tensor(out_from_scene, dtype=torch.float64))
    f_rest = np.transpose(moved.sh[:, 1:].numpy(), (0, 2, 1))  # [N, 3, K - 1], channel-major (INRIA)
    data = SplatData(
        means=moved.means.numpy(),
        f_dc=moved.sh[:, 0].numpy(),
        f_rest=f_rest,
        opacity=moved.opacity_logits.numpy(),
        scales=moved.log_scales.numpy(),
        quats=moved.quats.numpy(),
    )
    return data, int((~keep).sum())


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
    psnr_init = _score(splats, views, backend, bg, picks)

    extent = _extent(views)
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
    steps = _Steps(
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
    psnr_final = _score(splats, views, backend, bg, picks)

    final = sp.Splats(*(p.detach().cpu().double() for p in _shown(splats).parameters()))
    non_finite = int(sum((~torch.isfinite(p)).sum() for p in final.parameters()))
    out_from_scene = scene.source_from_scene() if config.frame == "user" else np.eye(4)
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
                "densification": _densification(steps, config),
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
                **_colour_left_out(config.sh_degree, fmt),
                "ssim_loss": "L1 only (3DGS adds 0.2 D-SSIM)",
                "held_out_score": "test views are not scored here (nerfpipe eval OUT.ply scores them)",
            },
            frame=config.frame,
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
