"""Stage `splat`: a trained run -> 3-D Gaussian splats optimised against the training photos (INRIA PLY or .splat).

    nerfpipe splat RUN_DIR OUT.ply [--max-seconds 300] [--format auto|ply|splat] [--frame user|normalized]

Steps:
1. Initialisation from the field ("NeRF to splats"): `gaussians` x INIT_RAYS_PER_GAUSSIAN random pixels of the
   training views, each ray rendered with `Trained.render_rays`; a ray whose accumulated opacity reaches OPAQUE
   gives a Gaussian at its expected depth, coloured with the field's colour there (the render with the background
   taken out: (rgb - (1 - acc) bg) / acc), isotropic, its size the root mean square distance to its 3 nearest
   neighbours (scipy cKDTree), at least the pixel footprint t / f of its ray (the local sample spacing),
   opacity INIT_OPACITY, SH degree 0.
2. Optimisation on the shared training loop (`model.loop`: budget, clock, non-finite recovery): each step renders one
   random training view whole and takes an Adam step on the L1 error against its photo (photos with alpha are
   put on the run's background, as the field was evaluated); learning rates are 3DGS's (means scaled by the scene's
   extent), decaying x LR_DECAY over the run. No densification or pruning during the run (left out).
3. Export: Gaussians with opacity below 1/255 are dropped (invisible); the rest go to the output frame
   (`--frame user`: `scene.source_from_scene()`, the user's frame viewers expect; `normalized`: the scene frame),
   in INRIA's PLY layout or the `.splat` layout (`data.splat_ply`). OUT.report.json next to it holds
   `out_from_scene` (4x4), the figures and the self-check; OUT.metrics.csv the step, seconds, loss and PSNR of
   each step's view (training seconds: the evaluation before and after is left out of the budget).

Backends (`backend`, decided once: `Backend`): gsplat's CUDA rasteriser when the device is CUDA and `import gsplat`
works, else `radiance.splats` (torch, any device); the report records which and why.
Self-check (report `check`): `psnr_gain`, the mean PSNR on EVAL_VIEWS training views after the optimisation less
before it (>= 0), and `non_finite` parameters (0). Held-out views are not scored (eval does not read splats yet).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.checks import Check, verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.masks import load_masked_image
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, config_to_json, sidecar, write_manifest
from nerfpipe.data.splat_ply import SplatData, write_ply, write_splat
from nerfpipe.model import OPAQUE, load_trained, resolve_device
from nerfpipe.model.loop import Budget, Clock, LoopSettings, Schedule, TrainingLoop
from nerfpipe.radiance import splats as sp
from nerfpipe.radiance.camera import OPENGL_FROM_OPENCV, Intrinsics, generate_rays
from nerfpipe.radiance.metrics import psnr_from_mse

__all__ = ["Config", "Outputs", "run", "Backend", "choose_backend", "VERSION"]

VERSION = "1"
INIT_RAYS_PER_GAUSSIAN = 2
INIT_OPACITY = 0.1
LRS = {"means": 1.6e-4, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh": 2.5e-3}
"""Adam learning rates per parameter (3DGS's; means' times the scene extent)."""
LR_DECAY = 0.1
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
    """Gaussians initialised from the field (fewer when fewer training rays hit something)."""
    frame: Literal["user", "normalized"] = "user"
    """Output frame: user (the source frame before convert, what viewers expect) | normalized (the scene frame)."""
    downscale: float | None = None
    """Optimise at 1/downscale of the photos (None: the factor the run trained at)."""
    backend: Literal["auto", "torch", "gsplat"] = "auto"
    """Rasteriser: auto (gsplat on CUDA when installed, else torch) | torch | gsplat."""
    seed: int = 0
    """Seed of the initial rays and the view order."""
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


# ---------------------------------------------------------------------------------------------- backends
@dataclass(frozen=True)
class Backend:
    """A rasteriser, chosen once: its name, why it was chosen, and its render."""

    name: str
    why: str
    render: Callable[[sp.Splats, Tensor, Intrinsics, Tensor], Tensor]
    """(splats, world_from_cam [4, 4], intrinsics, background [3]) -> rgb [H, W, 3]."""


def _torch_render(splats: sp.Splats, world_from_cam: Tensor, intr: Intrinsics, background: Tensor) -> Tensor:
    return sp.render(splats, world_from_cam, intr, background)["rgb"]


def choose_backend(asked: str, device: torch.device) -> Backend:
    """The backend for `asked` (auto | torch | gsplat) on `device` (module doc); UserError when gsplat cannot run."""
    if asked == "torch":
        return Backend("torch", "asked for", _torch_render)
    try:
        import gsplat  # noqa: F401

        found, missing = True, ""
    except ImportError as exc:
        found, missing = False, str(exc)
    if asked == "gsplat" and not (found and device.type == "cuda"):
        reason = "the device is not CUDA" if found else f"gsplat is not installed ({missing})"
        raise UserError(f"backend: gsplat cannot run here: {reason}; expected backend auto or torch")
    if found and device.type == "cuda":
        return Backend("gsplat", "CUDA device and gsplat installed", _gsplat_render)
    return Backend("torch", "the device is not CUDA" if found else "gsplat is not installed", _torch_render)


def _gsplat_render(splats: sp.Splats, world_from_cam: Tensor, intr: Intrinsics, background: Tensor) -> Tensor:
    from gsplat import rasterization

    like = splats.means
    cam_from_world_cv = torch.linalg.inv(torch.as_tensor(world_from_cam).to(like) @ OPENGL_FROM_OPENCV.to(like))
    ks = torch.tensor([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]]).to(like)
    colors, _, _ = rasterization(
        splats.means, splats.quats, torch.exp(splats.log_scales), torch.sigmoid(splats.opacity_logits), splats.sh,
        cam_from_world_cv[None], ks[None], intr.w, intr.h, sh_degree=sp.sh_degree(splats.sh.shape[1]),
        backgrounds=background.to(like)[None], near_plane=0.01, eps2d=sp.EPS2D,
    )  # fmt: skip
    return colors[0]


@dataclass
class _Views:
    """Training photos on the background (uint8 [H, W, 3] each) and their cameras."""

    photos: list[Tensor]
    world_from_cams: list[Tensor]  # [4, 4] float64 each
    intrinsics: list[Intrinsics]

    def target(self, k: int, device: torch.device) -> Tensor:
        return self.photos[k].to(device).float() / 255.0


def _load_views(scene: Any, indices: tuple[int, ...], downscale: float, background: np.ndarray) -> _Views:
    import cv2

    photos, poses, intrs = [], [], []
    for i in indices:
        intr = scene.frame_intrinsics(i)
        img = load_masked_image(scene, i)
        if img.shape[:2] != (intr.h, intr.w):
            raise UserError(f"{scene.image_path(i)}: image is {img.shape[1]}x{img.shape[0]}, transforms.json says "
                            f"{intr.w}x{intr.h}")  # fmt: skip
        if downscale != 1.0:
            intr = intr.scaled(1.0 / downscale)
            img = cv2.resize(img, (intr.w, intr.h), interpolation=cv2.INTER_AREA)
        if img.shape[-1] == 4:
            img = img[..., :3] * img[..., 3:] + background * (1 - img[..., 3:])
        photos.append(torch.from_numpy(np.round(np.clip(img[..., :3], 0, 1) * 255).astype(np.uint8)))
        poses.append(torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64))
        intrs.append(Intrinsics(w=intr.w, h=intr.h, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy))
    return _Views(photos, poses, intrs)


def _init_from_field(trained: Any, views: _Views, count: int, gen: torch.Generator) -> tuple[sp.Splats, dict]:
    """Gaussians where training rays end (module doc, step 1)."""
    from scipy.spatial import cKDTree

    sizes = torch.tensor([i.w * i.h for i in views.intrinsics], dtype=torch.float64)
    n_rays = count * INIT_RAYS_PER_GAUSSIAN
    per_view = torch.bincount(torch.multinomial(sizes, n_rays, replacement=True, generator=gen), minlength=len(sizes))
    pts, cols, foot = [], [], []
    bg = trained.background.detach().float().cpu().reshape(3)
    for k, m in enumerate(per_view.tolist()):
        intr = views.intrinsics[k]
        pix = torch.randint(intr.w * intr.h, (m,), generator=gen)
        uv = torch.stack([pix % intr.w, pix // intr.w], dim=-1).double() + 0.5
        o, d = generate_rays(intr, views.world_from_cams[k], uv)
        out = trained.render_rays(o.float(), d.float(), median=False)
        rgb, t, acc = (out[key].detach().float().cpu() for key in ("rgb", "depth", "acc"))
        hit = (acc >= OPAQUE) & torch.isfinite(t) & (t > 0)
        pts.append((o.float() + d.float() * t[:, None])[hit])
        cols.append(((rgb - (1 - acc[:, None]) * bg) / acc[:, None].clamp_min(1e-6)).clamp(0, 1)[hit])
        foot.append(t[hit] / max(intr.fx, intr.fy))
    means, colors, footprint = torch.cat(pts), torch.cat(cols), torch.cat(foot)
    if means.shape[0] < 4:
        raise UserError(f"{trained.scene.root}: fewer than 4 of {n_rays} training rays reach opacity {OPAQUE} in the "
                        "field: nothing to put Gaussians on (an empty or untrained run?)")  # fmt: skip
    keep = torch.randperm(means.shape[0], generator=gen)[:count]
    means, colors, footprint = means[keep], colors[keep], footprint[keep]
    dist, _ = cKDTree(means.numpy()).query(means.numpy(), k=4)
    knn = torch.from_numpy(np.sqrt(np.mean(dist[:, 1:] ** 2, axis=1))).float()
    scale = torch.maximum(knn, footprint).clamp_min(1e-7)
    n = means.shape[0]
    splats = sp.Splats(means=means, log_scales=torch.log(scale)[:, None].expand(n, 3).contiguous(),
                       quats=torch.tensor([1.0, 0, 0, 0]).expand(n, 4).contiguous(),
                       opacity_logits=torch.full((n,), math.log(INIT_OPACITY / (1 - INIT_OPACITY))),
                       sh=sp.rgb_to_sh0(colors)[:, None, :])  # fmt: skip
    used = {"rays": n_rays, "rays_hit": int(sum(p.shape[0] for p in pts)), "gaussians": n,
            "rule": f"expected depth of training rays with acc >= {OPAQUE}; colour (rgb - (1 - acc) bg) / acc; size "
                    "rms distance to 3 nearest neighbours, at least t / f; opacity 0.1; SH degree 0"}  # fmt: skip
    return splats, used


# ---------------------------------------------------------------------------------------------- optimisation
def _psnr(a: Tensor, b: Tensor) -> float:
    return psnr_from_mse(float(torch.mean((a.detach().float() - b.float()) ** 2)))


@dataclass(kw_only=True)
class _Steps:
    """The splat step on the shared loop (`model.loop.Stepper`; no checkpoints: the output is written at the end)."""

    splats: sp.Splats
    opt: torch.optim.Optimizer
    views: _Views
    backend: Backend
    background: Tensor
    gen: torch.Generator
    clock: Clock
    metrics: MetricsLog
    progress: Progress
    task: Any
    step: int = 0
    lr_factor: float = 1.0
    last: dict = field(default_factory=dict)

    def prepare(self, fraction: float) -> bool:
        return False

    def train_step(self, lr: float) -> bool:
        k = int(torch.randint(len(self.views.photos), (1,), generator=self.gen))
        device = self.splats.means.device
        target = self.views.target(k, device)
        rgb = self.backend.render(self.splats, self.views.world_from_cams[k], self.views.intrinsics[k], self.background)
        err = torch.mean(torch.abs(rgb - target))
        loss = float(err.detach())
        if not math.isfinite(loss):
            return False
        self.opt.zero_grad(set_to_none=True)
        err.backward()
        self.opt.step()
        self.last = {"loss": loss, "psnr": _psnr(rgb, target)}
        return True

    def log(self, lr: float) -> None:
        self.metrics.append(step=self.step, seconds=round(self.clock(), 4), loss=round(self.last["loss"], 6),
                            psnr=round(self.last["psnr"], 4))  # fmt: skip
        self.progress.advance(self.task)

    def snapshot(self) -> tuple[list[Tensor], dict]:
        return [p.detach().clone() for p in self.splats.parameters()], copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[list[Tensor], dict]) -> None:
        with torch.no_grad():
            for p, kept in zip(self.splats.parameters(), snapshot[0], strict=True):
                p.copy_(kept)
        self.opt.load_state_dict(snapshot[1])

    def checkpoint(self, seconds: float) -> None:
        pass

    def finish(self, seconds: float) -> None:
        pass


@torch.no_grad()
def _score(splats: sp.Splats, views: _Views, backend: Backend, background: Tensor, picks: list[int]) -> float:
    device = splats.means.device
    return float(np.mean([_psnr(backend.render(splats, views.world_from_cams[k], views.intrinsics[k], background),
                                views.target(k, device)) for k in picks]))  # fmt: skip


def _extent(views: _Views) -> float:
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
    if config.downscale is not None and not config.downscale > 0:
        raise UserError(f"downscale: expected > 0, got {config.downscale}")
    return _out_format(config)


def _to_file(splats: sp.Splats, out_from_scene: np.ndarray) -> tuple[SplatData, int]:
    """Visible Gaussians in the output frame, as the files store them; and how many were dropped."""
    keep = torch.sigmoid(splats.opacity_logits) >= sp.ALPHA_MIN
    moved = sp.transformed(splats.subset(keep), torch.as_tensor(out_from_scene, dtype=torch.float64))
    n = len(moved)
    data = SplatData(means=moved.means.numpy(), f_dc=moved.sh[:, 0].numpy(), f_rest=np.zeros((n, 3, 0)),
                     opacity=moved.opacity_logits.numpy(), scales=moved.log_scales.numpy(),
                     quats=moved.quats.numpy())  # fmt: skip
    return data, int((~keep).sum())


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Splats from RUN_DIR (module doc)."""
    started = time.time()
    fmt = _validate(config)
    out = Path(config.out)
    device = resolve_device(config.device)
    backend = choose_backend(config.backend, device)
    trained = load_trained(config.run_dir, device)
    scene = trained.scene
    train_idx = scene.split("train")
    downscale = config.downscale or float(trained.run_config.get("downscale") or 1.0)
    background = trained.background.detach().float().cpu().reshape(3)
    views = _load_views(scene, train_idx, downscale, background.numpy())
    gen = torch.Generator().manual_seed(config.seed)
    splats, init = _init_from_field(trained, views, config.gaussians, gen)
    splats = sp.Splats(*(p.to(device).requires_grad_(True) for p in splats.parameters()))
    bg = background.to(device)
    picks = sorted({int(i) for i in np.linspace(0, len(train_idx) - 1, min(EVAL_VIEWS, len(train_idx))).round()})
    psnr_init = _score(splats, views, backend, bg, picks)

    extent = _extent(views)
    scales = {**LRS, "means": LRS["means"] * extent}
    opt = torch.optim.Adam([{"params": [p], "lr": scales[name], "lr_scale": scales[name]}
                            for name, p in zip(LRS, splats.parameters(), strict=True)], eps=1e-15)  # fmt: skip
    metrics = MetricsLog(sidecar(out, "metrics.csv"), ["step", "seconds", "loss", "psnr"])
    progress = progress or NO_PROGRESS
    clock, task = Clock(), progress.add_task("splat", total=config.max_steps)
    steps = _Steps(splats=splats, opt=opt, views=views, backend=backend, background=bg, gen=gen, clock=clock,
                   metrics=metrics, progress=progress, task=task)  # fmt: skip
    settings = LoopSettings(name="splat", budget=Budget(max_steps=config.max_steps, max_seconds=config.max_seconds),
                            schedule=Schedule(lr=1.0, decay=LR_DECAY))  # fmt: skip
    seconds = TrainingLoop(settings, steps, clock).run() if config.max_steps > 0 else 0.0
    psnr_final = _score(splats, views, backend, bg, picks)

    final = sp.Splats(*(p.detach().cpu().double() for p in splats.parameters()))
    non_finite = int(sum((~torch.isfinite(p)).sum() for p in final.parameters()))
    out_from_scene = scene.source_from_scene() if config.frame == "user" else np.eye(4)
    data, dropped = _to_file(final, out_from_scene)
    checks = [
        Check.lower("psnr_gain", psnr_final - psnr_init, 0.0, "the optimisation made the splats worse than their "
                    "initialisation on the training views: a learning rate too high, or the wrong photos", "dB"),
        Check.upper("non_finite", non_finite, 0, "NaN or inf in the Gaussians' parameters: the optimisation diverged"),
    ]  # fmt: skip
    # OUT takes its name only after its report is written: a failure in between leaves no OUT that looks done
    with atomic_path(out) as tmp:
        (write_ply if fmt == "ply" else write_splat)(tmp, data)
        metrics.save()
        report = write_manifest(
            out.parent, name=sidecar(out, "report.json").name, stage="splat", started=started, version=VERSION,
            inputs=[Path(config.run_dir) / "checkpoint.pt", Path(config.run_dir) / "config.json"],
            outputs=[out, metrics.path],
            used={"backend": backend.name, "backend_why": backend.why, "device": str(device), "format": fmt,
                  "init": init, "views": len(train_idx), "downscale": downscale, "scored_views": picks,
                  "loss": "L1 on one whole training view per step", "learning_rates": scales, "lr_decay": LR_DECAY,
                  "scene_extent": extent, "background": background.tolist(), "dropped_invisible": dropped,
                  "camera_model": "pinhole (distortion coefficients are not applied)"},
            left_out={"densification": "no splitting, cloning or pruning during the optimisation (fixed count)",
                      "view_dependent_colour": "SH degree 0 only (rotating higher degrees to the user's frame is not "
                                               "implemented)",
                      "ssim_loss": "L1 only (3DGS adds 0.2 D-SSIM)",
                      "held_out_score": "test views are not scored here (eval does not read splats yet)"},
            frame=config.frame, out_from_scene=out_from_scene.tolist(), gaussians=len(data), steps=steps.step,
            seconds=round(seconds, 3), psnr_train_init=round(psnr_init, 4), psnr_train_final=round(psnr_final, 4),
            config=config_to_json(config), **verdict(checks),
        )  # fmt: skip
    return Outputs(out=out, report=report, metrics=metrics.path, gaussians=len(data), steps=steps.step,
                   seconds=seconds, psnr_init=psnr_init, psnr_final=psnr_final, backend=backend.name)  # fmt: skip
