"""`train` stage: fit a radiance field to a posed scene (`transforms.json`) and write a run directory.

Run directory (docs/DESIGN.md "Trained run directory"):
  config.json, checkpoint.pt (`model.checkpoint`: tensors and primitive containers only, loads with
  weights_only=True), metrics.csv (step, seconds, loss, train_psnr, test_psnr (blank when not evaluated), lr,
  samples_per_ray, skip_fraction), psnr_vs_time.png, manifest.json (written last).

Reruns and reliability (docs/RELIABILITY.md): the run folder is locked while train writes there
(`data.lock`); a folder holding a run (checkpoint.pt or manifest.json) is refused unless `--resume` (continue:
the manifest is removed until the run ends again) or `--overwrite` (the old run goes to RUN_DIR.previous/, deleted
when the new run succeeds). Ctrl-C or SIGTERM saves a checkpoint at the current step and exits 130/143 with one
line; a checkpoint is also written every `checkpoint_seconds`. The manifest records the checkpoint's sha256.

The story: `_setup` reads the scene and builds (or resumes) the field model (`model.field_model`), `Loop.run`
optimises it (`stages.train.loop`), `_final_eval` renders evenly spaced test views in full, and the manifest
records what was used and left out (`stages.train.report`).

Conventions: rays in the scene frame, unit directions, t = Euclidean distance (radiance.camera).
Training draws random rays across all train views (colours held as uint8, rays made per batch from each view's
camera; `stages.train.views`). RGBA scenes composite a random background per ray during training and white for
evaluation. Fields: `fast` (TensoRF VM, occupancy-grid marching, coarse-to-fine upsampling) and `vanilla` (the
NeRF paper: 64 stratified + 128 importance samples, coarse and fine networks).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from data.atomic import write_json
from data.checks import verdict
from data.errors import Interrupted, UserError
from data.progress import NO_PROGRESS, Progress
from data.rundir import MetricsLog, config_to_json, output_folder, write_manifest
from data.sparse_depth import KEY as SPARSE_KEY
from data.sparse_depth import read_sparse_depth
from data.stop import stop_on_signals
from data.transforms import Scene, read_scene
from model.appearance import EVAL_RULE as APPEARANCE_EVAL_RULE
from model.appearance import Appearance
from model.camera_opt import CameraOpt, CameraSchedule, pivot_depths, pose_report, write_refined_transforms
from model.checkpoint import read_checkpoint, restore_appearance, restore_background, restore_space
from model.device import cpu_threads, resolve_device
from model.field_model import ModelSettings, build_model, make_space
from radiance.space import SPACES, Space
from stages.train.checks import train_checks
from stages.train.defaults import resolve_defaults
from stages.train.loop import DepthRays, Loop, TrainingDiverged, evaluate_psnr, make_optimizer
from stages.train.report import per_view_report, plot_psnr, used_and_left_out
from stages.train.views import auto_downscale, evenly_spaced, load_views

__all__ = ["Config", "Outputs", "run", "TrainingDiverged", "evenly_spaced"]

VERSION = "1"
DEPTH_LOSS = 0.01
"""Default `--depth-loss` weight where sparse points exist (contracted scenes)."""
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
    device: str = "auto"
    """torch device: auto (CUDA when available, else CPU), cpu, cuda, cuda:N."""
    seed: int = 0
    """Seed for initialisation and ray batches."""
    resume: bool = False
    """Continue from run_dir/checkpoint.pt (step count, optimizer state and elapsed time continue)."""
    overwrite: bool = False
    """Replace the run already in run_dir (set aside in RUN_DIR.previous/ until this run succeeds); without it,
    or --resume, train refuses a folder that holds a run."""
    batch_rays: int | None = None
    """Rays per optimizer step (None: 1024 on CPU, 8192 on CUDA; stages.train.defaults)."""
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
    """Write checkpoint.pt every this many steps (and at the end, and on Ctrl-C or SIGTERM)."""
    checkpoint_seconds: float = 60.0
    """Also write checkpoint.pt every this many seconds of wall-clock time, so a killed run loses at most that
    (0: off)."""
    scene_model: Literal["auto", "box", "ndc", "contract"] = "auto"
    """Where the field lives: auto, box, ndc or contract. box: the scene's aabb (objects on a plain or
    transparent background). ndc: normalised device coordinates of the mean camera (forward-facing captures;
    NeRF's LLFF mode, `radiance.ndc`). contract: the scene's box at full resolution and all space beyond it
    contracted into a shell (mip-NeRF 360 / nerfacto; `radiance.contraction`): captures that see a room or a
    landscape. auto: ndc when forward-facing, box with alpha or a plain background, contract otherwise."""
    background: Literal["auto", "black", "white", "random", "learned"] = "auto"
    """What empty space shows: auto, black, white, random or learned. auto: random per ray for images with
    alpha (white at evaluation), the border colour when >= 90 % of the views' border pixels are one colour
    (tiny-NeRF's black, renders on white), a learned colour otherwise (`stages.train.defaults`)."""
    view_dependent: bool | None = None
    """Colour depends on view direction (None: on for every scene; off suits Lambertian scenes)."""
    resolution: tuple[int, int] | None = None
    """fast: grid resolution per axis at the start and at the end (coarse-to-fine upsampling). None: the scene
    kind's rule (stages.train.defaults.RULES): objects and contracted scenes from the object's size in pixels
    (lego_100 -> 64,160, lego_400 -> 96,300), forward-facing (NDC) scenes from the image's width."""
    upsample_at: tuple[float, ...] | None = None
    """fast: run-progress fractions at which the grid is upsampled (geometric steps to the final size). None:
    0.05,0.1,0.2,0.3; with refine_poses 0.2,0.3,0.4,0.5 (coarse-to-fine, `stages.train.defaults`)."""
    step_ratio: float | None = None
    """fast: marching step in voxels of the final grid (None: the scene kind's rule: objects 2 below a 200 grid,
    else 1; contracted 2 on CPU; NDC a fixed number of steps across inverse depth)."""
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
    tv: float | None = None
    """fast: weight of TensoRF's total-variation prior on the field's planes (`TensoRF.tv`; TensoRF's LLFF setting
    is 0.01). None: the scene kind's rule (stages.train.defaults.RULES): 0.01 for contracted scenes (real captures,
    where a VM field otherwise paints streaks and floaters into sparsely seen space: fox held-out 13.7 -> 17.8 dB),
    NDC's own measured weight, 0 for box scenes (objects)."""
    depth_loss: float | None = None
    """fast, contracted scenes: weight of DS-NeRF's depth loss on rays through the sparse points each training
    photo observed (transforms.json's `sparse_depth_path`, written by `convert` from COLMAP; data.sparse_depth).
    None: DEPTH_LOSS when the scene has them and is contracted, else 0 (and the manifest says why)."""
    distortion: float = 0.0
    """fast, contracted scenes: weight of mip-NeRF 360's distortion loss (its lambda is 0.01), which pulls each
    ray's weight into one compact peak (radiance.regularizers). Off by default: on the fox (300 s budget, CPU) it
    left held-out PSNR where it was (13.2 dB at 150 s with 0.01 and without): the field there is undertrained
    (0.3 epochs), not foggy by choice."""
    final_eval_views: int | None = None
    """Test views rendered in full at the end, evenly spaced over the test split (None: as many as fit in
    `final_eval_fraction` of max_seconds at the measured render speed, at least 1; `eval` scores them all).
    Evenly spaced: the NeRF Blender test views follow a path, so the first k views are one arc."""
    downscale: float | None = None
    """Train and evaluate on images shrunk by this factor (area filter). None: the smallest power of two that
    brings the long side to <= 800 px on CPU, <= 1600 px on CUDA (nerfstudio's auto downscale; a phone's
    1080x1920 trains at 270x480 on CPU, where the grid could not use more pixels in the time)."""
    final_eval_fraction: float = 0.1
    """Budget of the final full-image evaluation, as a fraction of max_seconds (when final_eval_views is None)."""
    threads: int | None = None
    """CPU: torch intra-op threads during the run (None: torch's default). On a shared or oversubscribed CPU,
    1 can be many times faster than 2 (measured 0.16 s vs 2.0 s per step on the 2-core dev machine)."""
    refine_poses: bool = False
    """Refine the training cameras jointly with the field (NeRF--): a per-camera SE(3) correction with its own
    Adam, learning rate and warm-up (`model.camera_opt`). The refined cameras are saved in the run (render,
    depth, mesh and eval use them; test views are mapped into the refined frame by a similarity) and written
    to RUN_DIR/transforms.json; the manifest lists each camera's correction."""
    refine_focal: bool = False
    """With refine_poses: also refine one focal-length scale shared by every camera."""
    camera_lr: float = 1e-2
    """refine_poses: the corrections' learning rate (radians and scene units per step, Adam), reached after
    the warm-up and decayed like the field's. 48 px scene, 3 deg / 3 % perturbations, 1000 steps with the
    coarse-to-fine grid: median rotation error 3.02 -> 0.67 deg at 5e-3, -> 0.55 deg at 1e-2 (2e-2 without
    coarse-to-fine drifted to 20 deg)."""
    appearance: bool = False
    """Learn a small appearance code per training image (NeRF-W) that changes colour only (exposure, white
    balance, colour cast; density is shared); novel views render with the mean code (`model.appearance`)."""


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
    if config.scene_model != "auto" and config.scene_model not in SPACES:
        raise UserError(f"unknown scene model {config.scene_model!r}: expected auto, {', '.join(SPACES)}")
    if config.background not in ("auto", "black", "white", "random", "learned"):
        raise UserError(f"unknown background {config.background!r}: expected auto, black, white, random or learned")
    if config.max_steps < 0 or not config.max_seconds > 0:
        raise UserError(f"expected max_steps >= 0 and max_seconds > 0, got {config.max_steps}, {config.max_seconds}")
    if config.batch_rays is not None and config.batch_rays < 1:
        raise UserError(f"expected batch_rays >= 1, got {config.batch_rays}")
    if config.lr is not None and not config.lr > 0:
        raise UserError(f"expected lr > 0, got {config.lr}")
    if not config.distortion >= 0:
        raise UserError(f"expected distortion >= 0, got {config.distortion}")
    if config.tv is not None and not config.tv >= 0:
        raise UserError(f"--tv: expected >= 0, got {config.tv}")
    if config.resume and config.overwrite:
        raise UserError("pass either --resume (continue the run) or --overwrite (replace it), not both")
    if config.checkpoint_every < 1 or not config.checkpoint_seconds >= 0:
        raise UserError(f"expected checkpoint_every >= 1 and checkpoint_seconds >= 0, got "
                        f"{config.checkpoint_every}, {config.checkpoint_seconds}")  # fmt: skip
    if not config.camera_lr > 0:
        raise UserError(f"expected camera_lr > 0, got {config.camera_lr}")
    if config.refine_focal and not config.refine_poses:
        raise UserError("refine_focal needs refine_poses")
    if config.threads is not None and config.threads < 1:
        raise UserError(f"expected threads >= 1, got {config.threads}")
    if config.resolution is not None and (len(config.resolution) != 2 or min(config.resolution) < 2):
        raise UserError(f"expected resolution (start, end) >= 2, got {config.resolution}")
    if config.downscale is not None and not config.downscale >= 1:
        raise UserError(f"expected downscale >= 1, got {config.downscale}")
    if not (config.final_eval_fraction > 0):
        raise UserError(f"expected final_eval_fraction > 0, got {config.final_eval_fraction}")
    if not ((config.step_ratio is None or config.step_ratio > 0) and 0 < config.render_step_factor <= 1):
        raise UserError(f"expected step_ratio > 0 and 0 < render_step_factor <= 1, got {config.step_ratio}, "
                        f"{config.render_step_factor}")  # fmt: skip


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Train a field on config.scene_dir into config.run_dir (see the module docstring).

    progress: the CLI's display (`data.progress`); None trains silently.
    """
    _validate(config)
    marks = ("checkpoint.pt", "manifest.json")
    with output_folder(config.run_dir, overwrite=config.overwrite, resume=config.resume, marks=marks):
        with cpu_threads(config.threads):
            return _run(config, progress or NO_PROGRESS)


def _run(config: Config, progress: Progress) -> Outputs:
    started = time.time()
    loop, scene, scene_path, record = _setup(config, progress)
    config = loop.config
    (Path(config.run_dir) / "manifest.json").unlink(missing_ok=True)  # resumed: not a finished run until the end
    with stop_on_signals() as stop:
        loop.stop = stop
        seconds = loop.run()
    if stop.signum is not None:  # the signal came during the last checkpoint: it holds the final step
        raise Interrupted(f"interrupted ({stop.name}) at step {loop.step} after {seconds:.1f} s; continue with "
                          f"--resume (checkpoint {loop.ckpt_path})", stop.signum)  # fmt: skip
    test_psnr, chosen = _final_eval(config, loop, seconds)
    run_dir = Path(config.run_dir)
    plot = run_dir / "psnr_vs_time.png"
    plot_psnr(plot, loop.metrics.rows, f"train {config.field} on {scene_path.name}")
    train_idx, test_idx = scene.split("train"), scene.split("test") or scene.split("val")
    used, left_out = used_and_left_out(
        scene=scene, model=loop.model, device=loop.device, batch_rays=loop.batch_rays, steps=loop.step,
        seconds=seconds, samples_per_ray=loop.samples_per_ray, train_idx=train_idx,
        test_idx=test_idx, chosen=chosen, test_psnr=test_psnr,
    )  # fmt: skip
    used["defaults"] = record
    outputs = [run_dir / n for n in ("config.json", "checkpoint.pt", "metrics.csv", "psnr_vs_time.png")]
    used["per_view"] = per_view_report(run_dir, loop.model, scene, train_idx, config.downscale, seconds,
                                       loop.eval_rays_per_second, loop.device)  # fmt: skip
    outputs += [run_dir / f for f in used["per_view"]["files"]]
    outputs += _refinement_records(loop, scene, train_idx, used, left_out)
    checks = train_checks(rows=loop.metrics.rows, test_psnr=test_psnr, per_view=used["per_view"],
                          occupied=None if loop.model.grid is None else 1.0 - loop.model.grid.skip_fraction,
                          object_box=loop.model.space.object_box, pose=used.get("pose_refinement"))  # fmt: skip
    inputs = [scene_path / "transforms.json"] if scene_path.is_dir() else [scene_path]
    manifest = write_manifest(run_dir, stage="train", started=started, inputs=inputs, outputs=outputs, used=used,
                              left_out=left_out, version=VERSION, checkpoint_sha256=loop.ckpt_sha256,
                              **verdict(checks))  # fmt: skip
    return Outputs(run_dir=run_dir, checkpoint=loop.ckpt_path, metrics=loop.metrics.path, plot=plot,
                   manifest=manifest, steps=loop.step, seconds=seconds, test_psnr=test_psnr)  # fmt: skip


def _refinement_records(loop: Loop, scene: Scene, train_idx: tuple[int, ...], used: dict, left_out: dict) -> list:
    """Pose refinement and appearance in the manifest; the refined cameras' transforms.json (its path, or [])."""
    if loop.model.appearance is not None:
        used["appearance"] = {"codes": loop.model.appearance.n_views, "dim": loop.model.appearance.dim,
                              "evaluation": APPEARANCE_EVAL_RULE}  # fmt: skip
    else:
        left_out["appearance"] = "off (train --appearance): every image is assumed to share one appearance"
    if loop.cameras is None:
        left_out["pose_refinement"] = "off (train --refine-poses): the input cameras are taken as exact"
        return []
    used["pose_refinement"] = pose_report(loop.cameras, scene, train_idx)
    path = Path(loop.config.run_dir) / "transforms.json"
    return [write_refined_transforms(scene, loop.cameras.to_dict(), train_idx, path)]


def _setup(config: Config, progress: Progress) -> tuple[Loop, Scene, Path, dict]:
    """Read the scene and its rays, resolve the defaults, build the model (or restore it with --resume), write
    the resolved config.json. Returns the loop, the scene, its path and the manifest's `resolved` record."""
    device = resolve_device(config.device)
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
    train_idx = scene.split("train")
    test_idx = scene.split("test") or scene.split("val")
    downscale = config.downscale or auto_downscale(scene, train_idx, 1600 if device.type == "cuda" else 800)
    train = load_views(scene, train_idx, downscale)
    test = load_views(scene, test_idx, downscale) if test_idx else None
    found = resolve_defaults(config, scene, train, train_idx, device, downscale)
    if found.plain_colour is not None:
        shares = [views.mask_colour(found.plain_colour) for views in ((train, test) if test is not None else (train,))]
        found.reasons["background"] += (f"; {shares[0]:.1%} of the training pixels (the plain colour's regions "
                                        "that touch the image border) made transparent")  # fmt: skip
    space, model_reason = found.space, found.reasons["scene_model"]
    resolution, step_ratio, tv = found.resolution, found.step_ratio, found.tv
    if config.distortion > 0 and not space.distortion_loss:
        raise UserError(f"--distortion applies to contracted scenes only (this one is {model_reason})")
    depth_rays, depth_weight, depth_reason = _depth_rays(config, scene, train_idx, space)
    resolved = dataclasses.replace(config, resolution=resolution, step_ratio=step_ratio, tv=tv, depth_loss=depth_weight,
                                   batch_rays=found.batch_rays, downscale=downscale,
                                   upsample_at=found.upsample_at)  # fmt: skip
    if state is not None:
        space = restore_space(state, lambda kind: make_space(kind, scene))
        background = restore_background(state, device)
    else:
        background = found.background
    model = build_model(_settings(resolved), space, device, state["field_config"] if state else None, background)
    eval_px = None
    if test is not None:
        g = torch.Generator().manual_seed(config.seed + 1)
        n = test.n_rays  # randperm holds 8 bytes a pixel: above 16 M pixels, draw with replacement instead
        eval_px = (torch.randperm(n, generator=g)[: config.eval_pixels] if n <= 1 << 24
                   else torch.randint(n, (config.eval_pixels,), generator=g))  # fmt: skip

    if config.appearance:
        model.appearance = (restore_appearance(state, device) if state is not None else None) or Appearance(
            len(train_idx)
        ).to(device)
    cameras = _camera_opt(config, scene, train_idx, state, device)
    base_lr = config.lr if config.lr is not None else (0.03 if config.field == "fast" else 5e-4)
    opt = make_optimizer(model, base_lr)
    step, seconds_before, lr_factor = 0, 0.0, 1.0
    if state is not None:
        model.field.load_state_dict(state["field"])
        if model.grid is not None and state["occupancy"] is not None:
            model.grid.load_state_dict(state["occupancy"])
        opt = make_optimizer(model, base_lr)
        opt.load_state_dict(state["optimizer"])
        step, seconds_before, lr_factor = int(state["step"]), float(state["seconds"]), float(state["lr_factor"])
        gen.set_state(state["rng"])
    metrics = MetricsLog(run_dir / "metrics.csv", METRICS)
    if config.resume:
        metrics.load()
        metrics.rows = [r for r in metrics.rows if int(r["step"]) <= step]
    run_dir.mkdir(parents=True, exist_ok=True)
    _write_config(run_dir, resolved, scene_path)
    loop = Loop(config=resolved, model=model, opt=opt, base_lr=base_lr, train=train, test=test, eval_px=eval_px,
                batch_rays=found.batch_rays, gen=gen, device=device, metrics=metrics, ckpt_path=ckpt_path,
                progress=progress, step=step, seconds_before=seconds_before, lr_factor=lr_factor,
                cameras=cameras, depth_rays=depth_rays)  # fmt: skip
    record = {**found.reasons, "depth_loss": depth_reason,
              "resolved": {"resolution": list(resolution), "step_ratio": step_ratio,
                           "batch_rays": found.batch_rays, "background": model.background.describe(),
                           "tv": tv}}  # fmt: skip
    return loop, scene, scene_path, record


def _write_config(run_dir: Path, resolved: Config, scene_path: Path) -> None:
    """config.json: the resolved Config, its scene folder resolved (absolute) and also relative to the run folder
    (`scene_from_run`, tried first by `model.trained.load_trained`: a run moved with its scene still finds it)."""
    scene_abs = scene_path.resolve()
    doc = {**config_to_json(dataclasses.replace(resolved, scene_dir=scene_abs)),
           "scene_from_run": os.path.relpath(scene_abs, run_dir.resolve())}  # fmt: skip
    write_json(run_dir / "config.json", doc)


def _depth_rays(config: Config, scene: Scene, train_idx: tuple[int, ...],
                space: Space) -> tuple[DepthRays | None, float, str]:  # fmt: skip
    """(rays through the training photos' sparse points or None, the weight, why) for `Config.depth_loss`."""
    if config.depth_loss is not None and not config.depth_loss >= 0:
        raise UserError(f"--depth-loss: expected >= 0, got {config.depth_loss}")
    rel = scene.extra.get(SPARSE_KEY)
    if config.depth_loss == 0:
        return None, 0.0, "off (given)"
    if rel is None or not space.sparse_depth or config.field != "fast":
        why = (
            f"no {SPARSE_KEY} in transforms.json (sparse points come from COLMAP through convert)"
            if rel is None
            else f"applies to fast contracted scenes only (this one: {config.field}, {space.name})"
        )
        if config.depth_loss is not None:
            raise UserError(f"--depth-loss: {why}")
        return None, 0.0, f"left out: {why}"
    sparse = read_sparse_depth(scene.root / rel)
    os_, ds, depths, views = [], [], [], []
    for k, i in enumerate(train_idx):
        o, d, dist = sparse.rays(scene.frames[i].file_path, scene.frames[i].world_from_cam[:3, 3])
        os_.append(o), ds.append(d), depths.append(dist), views.append(np.full(len(dist), k))
    depth = np.concatenate(depths)
    if depth.size == 0:
        if config.depth_loss is not None:
            raise UserError(f"--depth-loss: {rel} has no points observed by the training photos")
        return None, 0.0, f"left out: {rel} has no points observed by the training photos"
    rays = DepthRays(torch.from_numpy(np.concatenate(os_)), torch.from_numpy(np.concatenate(ds)),
                     torch.from_numpy(depth), torch.from_numpy(np.concatenate(views)).long())  # fmt: skip
    weight = config.depth_loss if config.depth_loss is not None else DEPTH_LOSS
    return rays, weight, f"{weight} on {depth.size} sparse-point rays of {len(train_idx)} training photos"


def _camera_opt(config: Config, scene: Scene, train_idx: tuple[int, ...], state: dict | None,
                device: torch.device) -> CameraOpt | None:  # fmt: skip
    """The training cameras' corrections (restored on resume), or None without --refine-poses."""
    if not config.refine_poses:
        return None
    poses = np.stack([scene.frames[i].world_from_cam for i in train_idx])
    pivot = pivot_depths(poses, np.asarray(scene.aabb, dtype=np.float64).mean(0))
    cameras = CameraOpt(poses, focal=config.refine_focal, schedule=CameraSchedule(lr=config.camera_lr), pivot=pivot)
    cameras = cameras.to(device)
    if state is not None and state.get("camera_opt") is not None:
        cameras.load_dict(state["camera_opt"])
    return cameras


def _settings(config: Config) -> ModelSettings:
    return ModelSettings(
        field=config.field,
        resolution=config.resolution,
        step_ratio=config.step_ratio,
        occupancy_resolution=config.occupancy_resolution,
        render_step_factor=config.render_step_factor,
        view_dependent=config.view_dependent,
    )


def _final_eval(config: Config, loop: Loop, seconds: float) -> tuple[float | None, list[int]]:
    """Mean PSNR over evenly spaced full test images (None without a test split); logged to metrics.csv.
    Without final_eval_views, as many views as fit in final_eval_fraction x max_seconds at the render speed
    measured on the periodic evaluations (or on one view when there were none)."""
    loop.model.field.eval()
    test_psnr, chosen = None, []
    if loop.test is not None:
        n = len(loop.test.shapes)
        bg = loop.model.background.eval_colour().detach()
        k = config.final_eval_views
        if k is None:
            rate = loop.eval_rays_per_second or _rays_per_second(loop, bg)
            per_view = float(np.mean([h * w for h, w in loop.test.shapes]))
            k = max(1, min(n, int(config.final_eval_fraction * config.max_seconds * rate / per_view)))
        chosen = evenly_spaced(n, k)
        rays = loop.test_rays()
        psnrs = [evaluate_psnr(loop.model, loop.test, loop.test.pixels_of(v), bg, loop.device, rays) for v in chosen]
        test_psnr = float(np.mean(psnrs))
        loop.metrics.append(step=loop.step, seconds=round(seconds, 3), test_psnr=f"{test_psnr:.3f}")
    loop.metrics.save()
    return test_psnr, chosen


def _rays_per_second(loop: Loop, bg: torch.Tensor) -> float:
    idx = torch.arange(min(4096, loop.test.n_rays))
    t0 = time.perf_counter()
    evaluate_psnr(loop.model, loop.test, idx, bg, loop.device)
    return idx.numel() / max(time.perf_counter() - t0, 1e-6)
