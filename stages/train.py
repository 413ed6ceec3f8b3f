"""`train` stage: fit a radiance field to a posed scene (`transforms.json`) and write a run directory.

Run directory (docs/DESIGN.md "Trained run directory"):
  config.json, checkpoint.pt (tensors and primitive containers only: loads with weights_only=True),
  metrics.csv (step, seconds, loss, train_psnr, test_psnr (blank when not evaluated), lr, samples_per_ray,
  skip_fraction), psnr_vs_time.png, manifest.json (written last).

Conventions: rays in the scene frame, unit directions, t = Euclidean distance (radiance.camera).
Training draws random rays across all train views (pre-generated: directions float32, colours uint8).
RGBA scenes composite a random background per ray during training and white for evaluation.
The learning rate decays exponentially to 0.1x over the run; "progress" is the larger of the step and the
wall-clock fractions (max_steps, max_seconds), so a time budget gets the whole schedule.
Fields: `fast` (TensoRF VM, occupancy-grid marching, coarse-to-fine upsampling) and `vanilla` (the NeRF
paper: 64 stratified + 128 importance samples, coarse and fine networks).
"""

from __future__ import annotations

import copy
import math
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from data.atomic import atomic_path
from data.errors import UserError
from data.rundir import MetricsLog, write_config, write_manifest
from data.transforms import Scene, is_forward_facing, load_image, read_scene
from radiance.aabb import ray_aabb_segment
from radiance.camera import generate_rays
from radiance.fields import Field, TensoRF, VanillaNeRF, make_field
from radiance.ndc import NDC, fit_ndc
from radiance.occupancy import OccupancyGrid
from radiance.render import StratifiedSampler, render_marched, render_rays_hierarchical

__all__ = ["Config", "Outputs", "Trained", "run", "load_trained", "TrainingDiverged", "evenly_spaced"]

VERSION = "1"
CHECKPOINT_FORMAT = 1
METRICS = ["step", "seconds", "loss", "train_psnr", "test_psnr", "lr", "samples_per_ray", "skip_fraction"]
WHITE = (1.0, 1.0, 1.0)


@dataclass(frozen=True, kw_only=True)
class Config:
    scene_dir: Path
    """Folder with transforms.json (or the file itself)."""
    run_dir: Path
    """Output run directory (created)."""
    field: Literal["fast", "vanilla"] = "fast"
    """Field: "fast" (TensoRF VM + occupancy grid, the default) or "vanilla" (the NeRF paper's MLP)."""
    max_steps: int = 30000
    """Stop after this many optimizer steps (counted across resumes)."""
    max_seconds: float = 900.0
    """Stop after this many seconds of training (counted across resumes, periodic evaluation excluded)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """"auto": CUDA when available, else CPU."""
    seed: int = 0
    """Seed for initialisation and ray batches."""
    resume: bool = False
    """Continue from run_dir/checkpoint.pt (step count, optimizer state and elapsed time continue)."""
    batch_rays: int | None = None
    """Rays per optimizer step (None: 1024 on CPU, where more small steps beat fewer big ones in a fixed
    time budget (22.6 vs 18.1 dB after 30 s on a 128 px scene), 4096 on CUDA)."""
    lr: float | None = None
    """Base learning rate (None: 0.03 for fast grids (MLP at lr/20), 5e-4 for vanilla).
    Fast, lego_100, 120 s: 0.02 -> 31.0 dB, 0.03 -> 31.5 dB, 0.05 -> 31.1 dB (single runs, 2 idle CPU cores)."""
    lr_decay: float = 0.1
    """Final learning-rate factor reached at the end of the run (exponential decay)."""
    eval_every: int = 250
    """Evaluate test PSNR on `eval_pixels` held-out pixels every this many steps (0: only at the end)."""
    eval_pixels: int = 4096
    """Held-out pixels used for the periodic test PSNR (full test images are rendered at the end)."""
    log_every: int = 25
    """Write a metrics row every this many steps."""
    checkpoint_every: int = 1000
    """Write checkpoint.pt every this many steps (and at the end)."""
    scene_model: Literal["auto", "box", "ndc"] = "auto"
    """Where the field lives. box: the scene's aabb (bounded and 360-degree scenes). ndc: normalised device
    coordinates of the mean camera (forward-facing captures whose content reaches to infinity; NeRF's LLFF
    mode, `radiance.ndc`). auto: ndc when the cameras are forward-facing (convert's scene_type, else all
    within 45 degrees of their mean direction), box otherwise."""
    view_dependent: bool | None = None
    """Colour depends on view direction (None: on for every scene; off suits Lambertian scenes)."""
    resolution: tuple[int, int] = (64, 160)
    """fast: grid resolution per axis at the start and at the end (coarse-to-fine upsampling).
    lego_100, 120 s CPU: (64, 160) 30.0 dB, (48, 128) 29.4 dB, (64, 192) 29.6 dB."""
    upsample_at: tuple[float, ...] = (0.05, 0.1, 0.2, 0.3)
    """fast: run-progress fractions at which the grid is upsampled (geometric steps to the final size)."""
    step_ratio: float = 2.0
    """fast: marching step in voxels of the final grid."""
    render_step_factor: float = 0.5
    """fast: evaluation and rendering march at this fraction of the training step. The field is continuous, so
    finer quadrature at inference only costs render time: lego_100 after 120 s (trained at 2 voxels) 31.94 ->
    32.43 dB at 0.5 (0.25: 32.46 dB), lego_400 after 900 s (trained at 1 voxel) +0.15 dB; rays/s about halve."""
    occupancy_resolution: int = 64
    """fast: occupancy grid cells per axis."""
    occupancy_every: int = 16
    """fast: update the occupancy grid every this many steps."""
    density_l1: float = 0.0
    """fast: weight of the L1 sparsity prior on the density factors."""
    final_eval_views: int | None = None
    """Test views rendered in full at the end, evenly spaced over the test split (None: all). The NeRF
    Blender test views follow a path round the object, so the first k views are one arc, not a sample
    (lego_400: the first 25 score 29.7 dB where 25 evenly spaced score 32.5 dB)."""
    threads: int | None = None
    """CPU: torch intra-op threads during the run (None: torch's default). On a shared or oversubscribed CPU,
    1 can be many times faster than 2 (measured 0.16 s vs 2.0 s per step on the 2-core dev machine)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    run_dir: Path
    checkpoint: Path
    metrics: Path
    plot: Path
    manifest: Path
    steps: int
    seconds: float
    test_psnr: float | None
    """Mean PSNR over the full test images at the end (None when the scene has no test split)."""


class TrainingDiverged(RuntimeError):
    """The loss went non-finite repeatedly, even after restoring the last good state with a lower LR."""


# ----------------------------------------------------------------------------------------------------------
# Rendering: radiance.render's model-free renderers, given callbacks over the field. Both kinds return
# dict(rgb, depth, depth_median, acc, samples, ...); vanilla adds rgb_coarse.


def _render_fast(
    field: TensoRF,
    grid: OccupancyGrid,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    near: float,
    far: float,
    step_size: float,
    background: Tensor,  # [3] or [R, 3]
    jitter: bool = False,
    with_median: bool = False,
) -> dict[str, Tensor]:
    """TensoRF + occupancy grid: radiance.render.render_marched over the field's density and colour."""
    rgb_fn = None
    if field.has_color:
        rgb_fn = lambda x, d: field.color(x, d if field.view_dependent else None)  # noqa: E731
    out = render_marched(
        rays_o, rays_d, grid=grid, sigma_fn=field.density, rgb_fn=rgb_fn, near=near, far=far, step_size=step_size,
        background=background, jitter=jitter, with_median=with_median,
    )  # fmt: skip
    out["samples"] = torch.tensor(float(out["ray_indices"].numel()))
    return out


def _rgb_sigma(net, view_dependent: bool):
    """A NeRF MLP (x, d) -> (sigma, rgb | None) as render_rays' rgb_sigma_fn (rgb 0 for density-only)."""

    def fn(x: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        sigma, rgb = net(x, d if view_dependent else None)
        if rgb is None:
            rgb = torch.zeros(*sigma.shape, 3, dtype=sigma.dtype, device=sigma.device)
        return rgb, sigma

    return fn


def _render_vanilla(
    field: VanillaNeRF,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    aabb: Tensor,  # [2, 3]
    near: float,
    far: float,
    background: Tensor,  # [3] or [R, 3]
    jitter: bool,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """NeRF: n_coarse stratified samples in the box, n_fine importance samples, the fine net on all of them
    (radiance.render.render_rays_hierarchical)."""
    t_near, t_far = ray_aabb_segment(rays_o, rays_d, aabb, near, far)
    out = render_rays_hierarchical(
        rays_o, rays_d, near=t_near, far=t_far, n_fine=field.n_fine, background=background,
        coarse_sampler=StratifiedSampler(n_samples=field.n_coarse, jitter=jitter, generator=generator),
        coarse_fn=_rgb_sigma(field.coarse, field.view_dependent), fine_fn=_rgb_sigma(field.fine, field.view_dependent),
        jitter=jitter, generator=generator,
    )  # fmt: skip
    out["rgb_coarse"] = out["coarse"]["rgb"]
    out["samples"] = torch.tensor(float(out["coarse"]["t_starts"].numel() + out["t_starts"].numel()))
    return out


# ----------------------------------------------------------------------------------------------------------
# Data


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise UserError("device cuda requested but torch.cuda.is_available() is False")
    if name not in ("cpu", "cuda"):
        raise UserError(f"unknown device {name!r}: expected auto, cpu or cuda")
    return torch.device(name)


@dataclass
class _Views:
    """Rays of a set of views: origins per view, directions and colours per ray (flattened views)."""

    origins: Tensor  # [V, 3] float32
    view: Tensor  # [M] int32, view of each ray
    dirs: Tensor  # [M, 3] float32
    rgba: Tensor  # [M, 4] uint8 (alpha 255 for RGB images)
    shapes: list[tuple[int, int]]  # (h, w) per view

    def batch(self, idx: Tensor, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        o = self.origins[self.view[idx].long()].to(device)
        d = self.dirs[idx].to(device)
        c = self.rgba[idx].to(device).float() / 255.0
        return o, d, c[:, :3], c[:, 3]


def _load_views(scene: Scene, indices: tuple[int, ...]) -> _Views:
    origins, views, dirs, rgba, shapes = [], [], [], [], []
    for k, i in enumerate(indices):
        img = load_image(scene.image_path(i))
        intr = scene.frame_intrinsics(i)
        if img.shape[:2] != (intr.h, intr.w):
            raise UserError(f"{scene.image_path(i)}: image is {img.shape[1]}x{img.shape[0]}, "
                            f"transforms.json says {intr.w}x{intr.h}")  # fmt: skip
        if img.shape[-1] == 3:
            img = np.concatenate([img, np.ones_like(img[..., :1])], axis=-1)
        world_from_cam = torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64)
        o, d = generate_rays(intr, world_from_cam)
        origins.append(o[0].float())
        dirs.append(d.float())
        views.append(torch.full((d.shape[0],), k, dtype=torch.int32))
        rgba.append(torch.from_numpy(np.round(img.reshape(-1, 4) * 255).astype(np.uint8)))
        shapes.append((intr.h, intr.w))
    return _Views(torch.stack(origins), torch.cat(views), torch.cat(dirs), torch.cat(rgba), shapes)


def evenly_spaced(n: int, k: int | None) -> list[int]:
    """k indices spread evenly over range(n), first and last included (all n when k is None or >= n)."""
    if k is None or k >= n:
        return list(range(n))
    if k < 1:
        raise ValueError(f"expected k >= 1 views, got {k}")
    return sorted({int(i) for i in np.linspace(0, n - 1, k).round()})


def _composite_gt(rgb: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    return rgb * alpha[:, None] + (1 - alpha[:, None]) * background


def _psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-12))


# ----------------------------------------------------------------------------------------------------------
# Model state


@dataclass
class _Model:
    field: Field
    grid: OccupancyGrid | None
    kind: str
    step_size: float  # training march step (inference: step_size * render_step_factor)
    near: float
    far: float
    aabb: Tensor  # [2, 3] the field's box: scene frame, or NDC space when ndc is set
    ndc: NDC | None = None
    render_step_factor: float = 1.0

    @property
    def chunk(self) -> int:
        """Rays per evaluation chunk (vanilla: 256 samples x 256 activations per ray)."""
        return 8192 if self.kind == "fast" else 1024

    def render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen=None, median=False):
        """World rays o, d [R, 3] (unit d) -> dict(rgb, depth, depth_median, acc, ...); depths are distances
        along the world rays whatever space the field lives in."""
        if self.ndc is None:
            return self._render(o, d, background, train=train, gen=gen, median=median)
        o_n, d_n, valid = self.ndc.rays_to_ndc(o, d)
        out = self._render(o_n, d_n, background, train=train, gen=gen, median=median)
        for key in ("depth", "depth_median"):
            if key in out:
                out[key] = self.ndc.world_t(o, d, o_n, d_n, out[key])
        if not bool(valid.all()):  # rays away from the reference view see nothing (the dummy ray misses)
            out["depth"] = torch.where(valid, out["depth"], torch.zeros_like(out["depth"]))
        return out

    def _render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen=None, median=False):
        if self.kind == "fast":
            step = self.step_size if train else self.step_size * self.render_step_factor
            return _render_fast(self.field, self.grid, o, d, near=self.near, far=self.far, step_size=step,
                               background=background, jitter=train, with_median=median)  # fmt: skip
        return _render_vanilla(self.field, o, d, aabb=self.aabb, near=self.near, far=self.far, background=background,
                              jitter=train, generator=gen)  # fmt: skip


def _step_size(aabb: Tensor, resolution: int, ratio: float) -> float:
    return float((aabb[1] - aabb[0]).mean()) / resolution * ratio


def _fit_ndc(scene: Scene) -> NDC:
    """NDC of the scene's mean camera; its near plane is the scene's near bound."""
    if not (scene.near > 0 and math.isfinite(scene.near)):
        raise UserError(f"{scene.root}: NDC needs a near bound > 0 in transforms.json, got near={scene.near}")
    return fit_ndc(np.stack([f.world_from_cam for f in scene.frames]), scene.frame_intrinsics(0), scene.near)


def _uses_ndc(config: Config, scene: Scene) -> bool:
    if config.scene_model == "auto":
        return is_forward_facing(scene)
    return config.scene_model == "ndc"


def _build_model(config: Config, scene: Scene, device: torch.device, field_cfg: dict | None,
                 ndc: NDC | None = None) -> _Model:  # fmt: skip
    """The field, its occupancy grid (fast) and render settings. With `ndc`, the field's box is the NDC box
    of the training cameras (near 0, far: the box's end at infinity); otherwise the scene's aabb."""
    if ndc is None:
        aabb = torch.as_tensor(scene.aabb, dtype=torch.float32).reshape(2, 3)
        near, far = float(scene.near), (scene.far if math.isfinite(scene.far) else 1e10)
    else:
        poses = np.stack([f.world_from_cam for f in scene.frames])
        intr = [scene.frame_intrinsics(i) for i in range(len(scene.frames))]
        aabb = torch.as_tensor(ndc.box(poses, intr), dtype=torch.float32)
        near, far = 0.0, 1e10
    view_dep = True if config.view_dependent is None else config.view_dependent
    if field_cfg is None:
        if config.field == "fast":
            field_cfg = TensoRF(aabb=aabb, resolution=config.resolution[0], view_dependent=view_dep).config()
        else:
            field_cfg = VanillaNeRF(view_dependent=view_dep).config()
    field = make_field(field_cfg).to(device)
    grid = None
    if field_cfg["kind"] == "fast":
        grid = OccupancyGrid(aabb, config.occupancy_resolution).to(device)
    step = _step_size(aabb, config.resolution[1], config.step_ratio)
    return _Model(field, grid, field_cfg["kind"], step, near, float(far), aabb.to(device), ndc,
                  config.render_step_factor)  # fmt: skip


def _make_optimizer(field: Field, lr: float, *, fused: bool = True) -> torch.optim.Adam:
    """Adam; `fused` (one kernel per group, the same update up to float rounding) is the fast path: the plain
    per-tensor loop took half of a fast-field step on CPU (lego_100, 2 cores: 14.6 -> 23.4 steps/s at the final
    grid; 1599 -> 1989 steps in 120 s). fused=False is its plain twin (tests)."""
    return torch.optim.Adam(field.param_groups(lr), betas=(0.9, 0.99), fused=fused)


def _set_lr(opt: torch.optim.Optimizer, base: float) -> None:
    for g in opt.param_groups:
        g["lr"] = base * g.get("lr_scale", 1.0)


def _upsample_schedule(config: Config) -> list[tuple[float, int]]:
    r0, r1 = config.resolution
    n = len(config.upsample_at)
    if n == 0 or r0 == r1:
        return []
    res = [round(math.exp(math.log(r0) + (math.log(r1) - math.log(r0)) * (k + 1) / n)) for k in range(n)]
    return list(zip(config.upsample_at, res, strict=True))


def _save_checkpoint(path: Path, model: _Model, opt: torch.optim.Optimizer, step: int, seconds: float,
                     lr_factor: float, rng: Tensor) -> None:  # fmt: skip
    state = {
        "format": CHECKPOINT_FORMAT,
        "field_config": model.field.config(),
        "field": model.field.state_dict(),
        "occupancy": model.grid.state_dict() if model.grid is not None else None,
        "ndc": model.ndc.to_dict() if model.ndc is not None else None,
        "optimizer": opt.state_dict(),
        "step": step,
        "seconds": seconds,
        "lr_factor": lr_factor,
        "rng": rng,
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _read_checkpoint(path: Path, device) -> dict:
    if not path.is_file():
        raise UserError(f"{path}: no checkpoint to resume from")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # corrupt or foreign file
        raise UserError(f"{path}: cannot read checkpoint ({type(exc).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: not a nerfpipe train checkpoint (format {CHECKPOINT_FORMAT})")
    return state


# ----------------------------------------------------------------------------------------------------------
# Stage


def _validate(config: Config) -> None:
    if config.field not in ("fast", "vanilla"):
        raise UserError(f"unknown field {config.field!r}: expected fast or vanilla")
    if config.scene_model not in ("auto", "box", "ndc"):
        raise UserError(f"unknown scene model {config.scene_model!r}: expected auto, box or ndc")
    if config.max_steps < 0 or not config.max_seconds > 0:
        raise UserError(f"expected max_steps >= 0 and max_seconds > 0, got {config.max_steps}, {config.max_seconds}")
    if config.batch_rays is not None and config.batch_rays < 1:
        raise UserError(f"expected batch_rays >= 1, got {config.batch_rays}")
    if config.lr is not None and not config.lr > 0:
        raise UserError(f"expected lr > 0, got {config.lr}")
    if config.threads is not None and config.threads < 1:
        raise UserError(f"expected threads >= 1, got {config.threads}")
    if len(config.resolution) != 2 or min(config.resolution) < 2:
        raise UserError(f"expected resolution (start, end) >= 2, got {config.resolution}")
    if not (config.step_ratio > 0 and 0 < config.render_step_factor <= 1):
        raise UserError(f"expected step_ratio > 0 and 0 < render_step_factor <= 1, got {config.step_ratio}, "
                        f"{config.render_step_factor}")  # fmt: skip


@torch.no_grad()
def _eval(model: _Model, views: _Views, idx: Tensor, bg: Tensor, device) -> float:
    se, n, chunk = 0.0, 0, model.chunk
    for i in range(0, idx.numel(), chunk):
        o, d, rgb, alpha = views.batch(idx[i : i + chunk], device)
        pred = model.render(o, d, bg, train=False)["rgb"]
        se += float(((pred - _composite_gt(rgb, alpha, bg)) ** 2).sum())
        n += pred.numel()
    return _psnr(se / max(n, 1))


def _plot(path: Path, rows: list[dict], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for key, style in (("train_psnr", "-"), ("test_psnr", "o-")):
        pts = [(float(r["seconds"]), float(r[key])) for r in rows if r.get(key) not in (None, "")]
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=key.replace("_", " "), markersize=3)
    ax.set_xlabel("wall-clock seconds")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def run(config: Config, progress=None) -> Outputs:
    """Train a field on config.scene_dir into config.run_dir (see the module docstring).

    progress: optional callback given each metrics row (a dict) as it is logged.
    """
    _validate(config)
    threads_before = torch.get_num_threads()
    if config.threads:
        torch.set_num_threads(config.threads)
    try:
        return _run(config, progress)
    finally:
        torch.set_num_threads(threads_before)


def _run(config: Config, progress) -> Outputs:
    started = time.time()
    device = _device(config.device)
    batch_rays = config.batch_rays or (4096 if device.type == "cuda" else 1024)
    scene_path = Path(config.scene_dir)
    if not (scene_path.is_file() or (scene_path / "transforms.json").is_file()):
        raise UserError(f"{scene_path}: no transforms.json (run convert or scene first)")
    scene = read_scene(scene_path)
    run_dir = Path(config.run_dir)
    ckpt_path = run_dir / "checkpoint.pt"
    state = _read_checkpoint(ckpt_path, device) if config.resume else None
    if state is not None and state["field_config"]["kind"] != config.field:
        raise UserError(f"{ckpt_path}: checkpoint holds a {state['field_config']['kind']} field, "
                        f"config asks for {config.field}")  # fmt: skip
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    if state is not None:
        ndc = NDC.from_dict(state["ndc"]) if state.get("ndc") is not None else None
    else:
        ndc = _fit_ndc(scene) if _uses_ndc(config, scene) else None
    model = _build_model(config, scene, device, state["field_config"] if state else None, ndc)

    train_idx = scene.split("train")
    test_idx = scene.split("test") or scene.split("val")
    train = _load_views(scene, train_idx)
    test = _load_views(scene, test_idx) if test_idx else None
    rgba = scene.has_alpha or bool((train.rgba[:, 3] < 255).any())
    white = torch.tensor(WHITE, device=device)
    eval_px = None
    if test is not None:
        g = torch.Generator().manual_seed(config.seed + 1)
        eval_px = torch.randperm(test.dirs.shape[0], generator=g)[: config.eval_pixels]

    base_lr = config.lr if config.lr is not None else (0.03 if config.field == "fast" else 5e-4)
    opt = _make_optimizer(model.field, base_lr)
    step, seconds_before, lr_factor = 0, 0.0, 1.0
    if state is not None:
        model.field.load_state_dict(state["field"])
        if model.grid is not None and state["occupancy"] is not None:
            model.grid.load_state_dict(state["occupancy"])
        opt = _make_optimizer(model.field, base_lr)
        opt.load_state_dict(state["optimizer"])
        step, seconds_before, lr_factor = int(state["step"]), float(state["seconds"]), float(state["lr_factor"])
        gen.set_state(state["rng"])
    metrics = MetricsLog(run_dir / "metrics.csv", METRICS)
    if config.resume:
        metrics.load()
        metrics.rows = [r for r in metrics.rows if int(r["step"]) <= step]
    run_dir.mkdir(parents=True, exist_ok=True)
    write_config(run_dir, config)

    schedule = [(p, r) for p, r in _upsample_schedule(config)]
    t_start = time.perf_counter()
    paused = [0.0]  # seconds spent evaluating: not training time (schedule, budget and metrics exclude it)
    elapsed = lambda: seconds_before + time.perf_counter() - t_start - paused[0]  # noqa: E731
    good = (copy.deepcopy(model.field.state_dict()), copy.deepcopy(opt.state_dict()), step)
    failures, skip_fraction, samples_per_ray, loss_acc = 0, 0.0, 0.0, []
    model.field.train()
    while step < config.max_steps:
        frac = max(step / max(config.max_steps, 1), elapsed() / config.max_seconds)
        if frac >= 1.0:
            break
        if model.kind == "fast":
            while schedule and frac >= schedule[0][0]:
                _, res = schedule.pop(0)
                if res > model.field.resolution:
                    model.field.upsample(res)
                    opt = _make_optimizer(model.field, base_lr)
                    good = (copy.deepcopy(model.field.state_dict()), copy.deepcopy(opt.state_dict()), step)
            model.grid.update(model.field.density, step, every=config.occupancy_every, warmup_steps=64)
        lr = base_lr * lr_factor * config.lr_decay**frac
        _set_lr(opt, lr)
        idx = torch.randint(train.dirs.shape[0], (batch_rays,), generator=gen)
        o, d, rgb, alpha = train.batch(idx, device)
        bg = torch.rand(o.shape[0], 3, generator=gen).to(device) if rgba else white
        target = _composite_gt(rgb, alpha, bg)
        out = model.render(o, d, bg, train=True, gen=None)
        loss = torch.mean((out["rgb"] - target) ** 2)
        mse = float(loss.detach())
        if "rgb_coarse" in out:
            loss = loss + torch.mean((out["rgb_coarse"] - target) ** 2)
        if model.kind == "fast" and config.density_l1 > 0:
            loss = loss + config.density_l1 * model.field.density_l1()
        if not math.isfinite(float(loss.detach())):
            failures += 1
            if failures >= 3:
                raise TrainingDiverged(f"loss is not finite at step {step} after {failures} restores with lower "
                                       f"learning rates; last checkpoint kept in {ckpt_path}")  # fmt: skip
            field_state, opt_state, step = good
            model.field.load_state_dict(field_state)
            opt.load_state_dict(opt_state)
            lr_factor *= 0.5
            print(f"train: non-finite loss; restored step {step}, learning rate x{lr_factor}", file=sys.stderr)
            continue
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        loss_acc.append(mse)
        samples_per_ray = 0.9 * samples_per_ray + 0.1 * float(out["samples"]) / o.shape[0] if step > 1 else \
            float(out["samples"]) / o.shape[0]  # fmt: skip
        if model.grid is not None:
            skip_fraction = model.grid.skip_fraction
        if step % 100 == 0:
            good = (copy.deepcopy(model.field.state_dict()), copy.deepcopy(opt.state_dict()), step)
        evaluate = test is not None and config.eval_every > 0 and step % config.eval_every == 0
        if step % config.log_every == 0 or evaluate:
            model.field.eval()
            row = {"step": step, "seconds": round(elapsed(), 3), "loss": f"{np.mean(loss_acc):.6g}",
                   "train_psnr": f"{_psnr(float(np.mean(loss_acc))):.3f}", "lr": f"{lr:.4g}",
                   "samples_per_ray": f"{samples_per_ray:.2f}", "skip_fraction": f"{skip_fraction:.4f}"}  # fmt: skip
            if evaluate:
                t_eval = time.perf_counter()
                row["test_psnr"] = f"{_eval(model, test, eval_px, white, device):.3f}"
                paused[0] += time.perf_counter() - t_eval
            model.field.train()
            metrics.append(**row)
            loss_acc = []
            if progress is not None:
                progress(row)
        if step % config.checkpoint_every == 0:
            _save_checkpoint(ckpt_path, model, opt, step, elapsed(), lr_factor, gen.get_state())
            metrics.save()
    train_seconds = elapsed()
    if model.grid is not None:
        # Every cell once more: the saved grid must match the final field (render and mesh skip by it), not a
        # partial refresh from before the last steps moved the surface.
        model.grid.update(model.field.density, step, full=True, points_per_cell=4)
    _save_checkpoint(ckpt_path, model, opt, step, train_seconds, lr_factor, gen.get_state())

    model.field.eval()
    test_psnr, chosen = None, []
    if test is not None:
        chosen = evenly_spaced(len(test.shapes), config.final_eval_views)
        starts = np.cumsum([0] + [h * w for h, w in test.shapes])
        psnrs = [_eval(model, test, torch.arange(starts[v], starts[v + 1]), white, device) for v in chosen]
        test_psnr = float(np.mean(psnrs))
        metrics.append(step=step, seconds=round(train_seconds, 3), test_psnr=f"{test_psnr:.3f}")
    metrics.save()
    plot = run_dir / "psnr_vs_time.png"
    _plot(plot, metrics.rows, f"train {config.field} on {scene_path.name}")

    peak = torch.cuda.max_memory_allocated() if device.type == "cuda" else None
    used = {
        "batch_rays": batch_rays,
        "field": model.field.config(),
        "device": str(device),
        "cpu_threads": torch.get_num_threads() if device.type == "cpu" else None,
        "steps": step,
        "train_seconds": round(train_seconds, 3),
        "train_views": len(train_idx),
        "test_views": len(test_idx),
        "test_psnr_full_images": test_psnr,
        "test_views_full_eval": [test_idx[v] for v in chosen],
        "background": "random per ray in training, white for eval" if rgba else "none (opaque RGB images)",
        "view_dependent": model.field.view_dependent,
        "scene_type": "forward-facing" if is_forward_facing(scene) else "bounded / 360",
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_cuda_mb": round(peak / 2**20, 1) if peak is not None else None,
    }
    if model.grid is not None:
        used["occupancy_skip_fraction"] = round(model.grid.skip_fraction, 4)
        used["samples_per_ray"] = round(samples_per_ray, 2)
        used["march_step"] = {"train": model.step_size, "render": model.step_size * model.render_step_factor}
    used["scene_model"] = "ndc" if ndc is not None else "box"
    if ndc is not None:
        used["ndc"] = {**ndc.to_dict(), "box": model.aabb.tolist(),
                       "note": "field and occupancy grid live in NDC of the mean camera (radiance.ndc); depths "
                               "are mapped back to scene units"}  # fmt: skip
    left_out = {}
    if ndc is not None:
        left_out["aabb"] = "forward-facing: the field spans the NDC frustum (near plane to infinity), not the aabb"
    elif is_forward_facing(scene):
        left_out["ndc"] = "forward-facing scene trained in its aabb because scene_model=box was asked for"
    else:
        left_out["ndc"] = "bounded 360-degree scene: NDC only applies to forward-facing captures"
    if not rgba:
        left_out["background_model"] = "images are opaque: no background compositing"
    if test is None:
        left_out["test_psnr"] = "scene has no test or val split"
    if model.grid is None:
        left_out["occupancy_grid"] = "vanilla field uses the paper's stratified + hierarchical sampling"
    outputs = [run_dir / n for n in ("config.json", "checkpoint.pt", "metrics.csv", "psnr_vs_time.png")]
    manifest = write_manifest(run_dir, stage="train", started=started, inputs=[scene_path / "transforms.json"]
                              if scene_path.is_dir() else [scene_path], outputs=outputs, used=used,
                              left_out=left_out, version=VERSION)  # fmt: skip
    return Outputs(run_dir=run_dir, checkpoint=ckpt_path, metrics=metrics.path, plot=plot, manifest=manifest,
                   steps=step, seconds=train_seconds, test_psnr=test_psnr)  # fmt: skip


# ----------------------------------------------------------------------------------------------------------
# Consumers: render / depth / eval / mesh


@dataclass
class Trained:
    """A trained run, ready for rendering and queries (no grad, chunked)."""

    scene: Scene
    field: Field
    occupancy: OccupancyGrid | None
    aabb: Tensor  # [2, 3] scene frame (NDC runs: the scene's aabb, not the field's NDC box)
    background: Tensor  # [3] evaluation background
    device: torch.device
    _model: _Model

    @property
    def chunk(self) -> int:
        return self._model.chunk

    @torch.no_grad()
    def render_rays(self, rays_o: Tensor, rays_d: Tensor) -> dict[str, Tensor]:
        """rays_o, rays_d [R, 3] (unit) -> dict(rgb [R, 3], depth [R] (expected t), depth_median [R], acc [R]).

        depth is sum(w t) / acc; depth_median the t where the accumulated weight reaches 0.5 (inf when the
        ray never reaches it). Missing colour (density-only field) gives rgb = background.
        """
        if rays_o.shape != rays_d.shape or rays_o.ndim != 2 or rays_o.shape[-1] != 3:
            raise ValueError(f"expected rays_o, rays_d [R, 3], got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}")
        parts: dict[str, list[Tensor]] = {k: [] for k in ("rgb", "depth", "depth_median", "acc")}
        for i in range(0, rays_o.shape[0], self.chunk):
            o = rays_o[i : i + self.chunk].to(self.device, torch.float32)
            d = rays_d[i : i + self.chunk].to(self.device, torch.float32)
            out = self._model.render(o, d, self.background, train=False, median=True)
            if "rgb" not in out:
                out["rgb"] = self.background.expand(o.shape[0], 3)
            for k in parts:
                parts[k].append(out[k])
        return {k: torch.cat(v) if v else torch.zeros(0, device=self.device) for k, v in parts.items()}

    @property
    def ndc(self) -> NDC | None:
        """The NDC map when the field lives in NDC (forward-facing runs), else None."""
        return self._model.ndc

    @torch.no_grad()
    def density(self, x: Tensor) -> Tensor:
        """x [N, 3] scene frame -> sigma [N] >= 0 per scene unit.

        NDC runs: the NDC density times NDC length per scene length along the mean camera's ray through x
        (`radiance.ndc`); 0 before the near plane.
        """
        out = []
        for i in range(0, x.shape[0], self.chunk):
            xi = x[i : i + self.chunk].to(self.device, torch.float32)
            if self.ndc is None:
                out.append(self.field.density(xi))
                continue
            p, scale, front = self.ndc.density_query(xi)
            sigma = self.field.density(p.clamp(-2.0, 2.0))
            out.append(torch.where(front, sigma * scale, torch.zeros_like(sigma)))
        return torch.cat(out) if out else x.new_zeros(0)

    @torch.no_grad()
    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        """x [N, 3], d [N, 3] unit or None -> rgb [N, 3] in [0, 1].

        A view-dependent field given d = None is asked along (0, 0, -1) (looking straight down the up axis).
        """
        if not self.field.has_color:
            raise ValueError("this run's field is density-only: no colour")
        out = []
        for i in range(0, x.shape[0], self.chunk):
            xi = x[i : i + self.chunk].to(self.device, torch.float32)
            di = None
            if self.field.view_dependent:
                di = (
                    d[i : i + self.chunk].to(xi)
                    if d is not None
                    else torch.tensor([0.0, 0.0, -1.0]).to(xi).expand_as(xi)
                )
            if self.ndc is not None:
                if di is not None:
                    di = self.ndc.directions_to_ndc(xi, di)
                xi = self.ndc.points_to_ndc(xi)
            out.append(self.field.color(xi, di))
        return torch.cat(out) if out else x.new_zeros(0, 3)


def load_trained(run_dir: str | Path, device: str | torch.device = "auto") -> Trained:
    """Load RUN_DIR (config.json + checkpoint.pt) for rendering; UserError when it is not a finished run."""
    import json

    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    if not cfg_path.is_file():
        raise UserError(f"{run_dir}: not a train run directory (no config.json)")
    doc = json.loads(cfg_path.read_text())
    dev = _device(device) if isinstance(device, str) else torch.device(device)
    state = _read_checkpoint(run_dir / "checkpoint.pt", dev)
    config = Config(scene_dir=Path(doc["scene_dir"]), run_dir=run_dir, field=doc.get("field", "fast"),
                    resolution=tuple(doc.get("resolution", (64, 160))), step_ratio=float(doc.get("step_ratio", 2.0)),
                    occupancy_resolution=int(doc.get("occupancy_resolution", 64)),
                    render_step_factor=float(doc.get("render_step_factor", Config.render_step_factor)))  # fmt: skip
    try:
        scene = read_scene(config.scene_dir)
    except UserError as exc:
        raise UserError(f"{run_dir}: the run's scene cannot be read: {exc}") from None
    ndc = NDC.from_dict(state["ndc"]) if state.get("ndc") is not None else None
    model = _build_model(config, scene, dev, state["field_config"], ndc)
    model.field.load_state_dict(state["field"])
    if model.grid is not None and state["occupancy"] is not None:
        model.grid.load_state_dict(state["occupancy"])
    model.field.eval()
    background = torch.tensor(WHITE, device=dev)
    if ndc is None:
        occupancy, aabb = model.grid, model.aabb
    else:  # the grid and box are in NDC; consumers (mesh) work in the scene frame
        occupancy, aabb = None, torch.as_tensor(scene.aabb, dtype=torch.float32, device=dev).reshape(2, 3)
    return Trained(scene=scene, field=model.field, occupancy=occupancy, aabb=aabb, background=background,
                   device=dev, _model=model)  # fmt: skip
