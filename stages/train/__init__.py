"""`train` stage: fit a radiance field to a posed scene (`transforms.json`) and write a run directory.

Run directory (docs/DESIGN.md "Trained run directory"):
  config.json, checkpoint.pt (`model.checkpoint`: tensors and primitive containers only, loads with
  weights_only=True), metrics.csv (step, seconds, loss, train_psnr, test_psnr (blank when not evaluated), lr,
  samples_per_ray, skip_fraction), psnr_vs_time.png, manifest.json (written last).

The story: `_setup` reads the scene and builds (or resumes) the field model (`model.field_model`), `Loop.run`
optimises it (`stages.train.loop`), `_final_eval` renders evenly spaced test views in full, and the manifest
records what was used and left out (`stages.train.report`).

Conventions: rays in the scene frame, unit directions, t = Euclidean distance (radiance.camera).
Training draws random rays across all train views (pre-generated: directions float32, colours uint8;
`stages.train.views`). RGBA scenes composite a random background per ray during training and white for
evaluation. Fields: `fast` (TensoRF VM, occupancy-grid marching, coarse-to-fine upsampling) and `vanilla` (the
NeRF paper: 64 stratified + 128 importance samples, coarse and fine networks).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from data.errors import UserError
from data.progress import NO_PROGRESS, Progress
from data.rundir import MetricsLog, write_config, write_manifest
from data.transforms import Scene, read_scene
from model.checkpoint import read_checkpoint
from model.device import resolve_device
from model.field_model import ModelSettings, build_model, scene_ndc, uses_ndc
from model.trained import WHITE
from radiance.ndc import NDC
from stages.train.loop import Loop, TrainingDiverged, evaluate_psnr, make_optimizer
from stages.train.report import plot_psnr, used_and_left_out
from stages.train.views import evenly_spaced, load_views

__all__ = ["Config", "Outputs", "run", "TrainingDiverged", "evenly_spaced"]

VERSION = "1"
METRICS = ["step", "seconds", "loss", "train_psnr", "test_psnr", "lr", "samples_per_ray", "skip_fraction"]


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


def _settings(config: Config) -> ModelSettings:
    return ModelSettings(
        field=config.field,
        resolution=config.resolution,
        step_ratio=config.step_ratio,
        occupancy_resolution=config.occupancy_resolution,
        render_step_factor=config.render_step_factor,
        view_dependent=config.view_dependent,
    )


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Train a field on config.scene_dir into config.run_dir (see the module docstring).

    progress: the CLI's display (`data.progress`); None trains silently.
    """
    _validate(config)
    threads_before = torch.get_num_threads()
    if config.threads:
        torch.set_num_threads(config.threads)
    try:
        return _run(config, progress or NO_PROGRESS)
    finally:
        torch.set_num_threads(threads_before)


def _run(config: Config, progress: Progress) -> Outputs:
    started = time.time()
    loop, scene, scene_path = _setup(config, progress)
    seconds = loop.run()
    test_psnr, chosen = _final_eval(config, loop, seconds)
    run_dir = Path(config.run_dir)
    plot = run_dir / "psnr_vs_time.png"
    plot_psnr(plot, loop.metrics.rows, f"train {config.field} on {scene_path.name}")
    train_idx, test_idx = scene.split("train"), scene.split("test") or scene.split("val")
    used, left_out = used_and_left_out(
        scene=scene, model=loop.model, device=loop.device, batch_rays=loop.batch_rays, steps=loop.step,
        seconds=seconds, samples_per_ray=loop.samples_per_ray, rgba=loop.rgba, train_idx=train_idx,
        test_idx=test_idx, chosen=chosen, test_psnr=test_psnr,
    )  # fmt: skip
    outputs = [run_dir / n for n in ("config.json", "checkpoint.pt", "metrics.csv", "psnr_vs_time.png")]
    inputs = [scene_path / "transforms.json"] if scene_path.is_dir() else [scene_path]
    manifest = write_manifest(run_dir, stage="train", started=started, inputs=inputs, outputs=outputs, used=used,
                              left_out=left_out, version=VERSION)  # fmt: skip
    return Outputs(run_dir=run_dir, checkpoint=loop.ckpt_path, metrics=loop.metrics.path, plot=plot,
                   manifest=manifest, steps=loop.step, seconds=seconds, test_psnr=test_psnr)  # fmt: skip


def _setup(config: Config, progress: Progress) -> tuple[Loop, Scene, Path]:
    """Read the scene and its rays, build the model (or restore it with --resume), write config.json."""
    device = resolve_device(config.device)
    batch_rays = config.batch_rays or (4096 if device.type == "cuda" else 1024)
    scene_path = Path(config.scene_dir)
    if not (scene_path.is_file() or (scene_path / "transforms.json").is_file()):
        raise UserError(f"{scene_path}: no transforms.json (run convert or scene first)")
    scene = read_scene(scene_path)
    run_dir = Path(config.run_dir)
    ckpt_path = run_dir / "checkpoint.pt"
    state = read_checkpoint(ckpt_path, device) if config.resume else None
    if state is not None and state["field_config"]["kind"] != config.field:
        raise UserError(f"{ckpt_path}: checkpoint holds a {state['field_config']['kind']} field, "
                        f"config asks for {config.field}")  # fmt: skip
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    if state is not None:
        ndc = NDC.from_dict(state["ndc"]) if state.get("ndc") is not None else None
    else:
        ndc = scene_ndc(scene) if uses_ndc(config.scene_model, scene) else None
    model = build_model(_settings(config), scene, device, state["field_config"] if state else None, ndc)

    train_idx = scene.split("train")
    test_idx = scene.split("test") or scene.split("val")
    train = load_views(scene, train_idx)
    test = load_views(scene, test_idx) if test_idx else None
    rgba = scene.has_alpha or bool((train.rgba[:, 3] < 255).any())
    eval_px = None
    if test is not None:
        g = torch.Generator().manual_seed(config.seed + 1)
        eval_px = torch.randperm(test.dirs.shape[0], generator=g)[: config.eval_pixels]

    base_lr = config.lr if config.lr is not None else (0.03 if config.field == "fast" else 5e-4)
    opt = make_optimizer(model.field, base_lr)
    step, seconds_before, lr_factor = 0, 0.0, 1.0
    if state is not None:
        model.field.load_state_dict(state["field"])
        if model.grid is not None and state["occupancy"] is not None:
            model.grid.load_state_dict(state["occupancy"])
        opt = make_optimizer(model.field, base_lr)
        opt.load_state_dict(state["optimizer"])
        step, seconds_before, lr_factor = int(state["step"]), float(state["seconds"]), float(state["lr_factor"])
        gen.set_state(state["rng"])
    metrics = MetricsLog(run_dir / "metrics.csv", METRICS)
    if config.resume:
        metrics.load()
        metrics.rows = [r for r in metrics.rows if int(r["step"]) <= step]
    run_dir.mkdir(parents=True, exist_ok=True)
    write_config(run_dir, config)
    loop = Loop(config=config, model=model, opt=opt, base_lr=base_lr, train=train, test=test, eval_px=eval_px,
                rgba=rgba, batch_rays=batch_rays, gen=gen, device=device, metrics=metrics, ckpt_path=ckpt_path,
                progress=progress, step=step, seconds_before=seconds_before, lr_factor=lr_factor)  # fmt: skip
    return loop, scene, scene_path


def _final_eval(config: Config, loop: Loop, seconds: float) -> tuple[float | None, list[int]]:
    """Mean PSNR over evenly spaced full test images (None without a test split); logged to metrics.csv."""
    loop.model.field.eval()
    test_psnr, chosen = None, []
    if loop.test is not None:
        chosen = evenly_spaced(len(loop.test.shapes), config.final_eval_views)
        white = torch.tensor(WHITE, device=loop.device)
        psnrs = [evaluate_psnr(loop.model, loop.test, loop.test.pixels_of(v), white, loop.device) for v in chosen]
        test_psnr = float(np.mean(psnrs))
        loop.metrics.append(step=loop.step, seconds=round(seconds, 3), test_psnr=f"{test_psnr:.3f}")
    loop.metrics.save()
    return test_psnr, chosen
