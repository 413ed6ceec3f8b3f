"""train's setup: read the scene and its views, resolve the defaults (`stages.train.defaults`, the method's own
through `Method.prepare`), build the method's model (or restore it with --resume), its hooks, the cameras'
corrections and the optimiser, and write the resolved config.json.

config.json: the resolved Config (`Defaults.config`: no None left but final_eval_views, which the end of the run
writes as the number of views it rendered in full), `method` and the method's resolved options under `options`,
pose refinement's under `refine` (null without it), `scene_dir` resolved (absolute) and `scene_from_run` (the scene
folder relative to the run folder, tried first by `model.run.load_trained`: a run moved with its scene still finds
it),
`scene_sha256` (its transforms.json's) and, once resumed, `resumed` (`stages.train.resume`: `--resume` continues
the same run, with the same scene and the same settings but for budget ones).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.atomic import write_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import Progress
from nerfpipe.data.rundir import MetricsLog, config_to_json, scene_from_run
from nerfpipe.data.transforms import Scene, read_scene
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.camera_opt import CameraOpt, CameraSchedule, pivot_depths
from nerfpipe.model.checkpoint import read_checkpoint, restore_appearance
from nerfpipe.model.device import resolve_device
from nerfpipe.model.distributed import DataParallel
from nerfpipe.model.methods import Method, TrainModel, method_named, method_of_checkpoint
from nerfpipe.model.views import Views, load_views
from nerfpipe.stages.train.config import Config, RefineOptions
from nerfpipe.stages.train.defaults import Defaults, Photos, resolve_defaults, resolve_downscale
from nerfpipe.stages.train.loop import Loop, make_optimizer
from nerfpipe.stages.train.refine import PoseRefinement
from nerfpipe.stages.train.resume import resume_config, scene_sha256

__all__ = ["setup", "write_run_config", "METRICS"]

RECORD = ("scene_sha256", "resumed")
"""config.json's keys beside the Config: the scene's identity and one entry per resume (`stages.train.resume`)."""
METRICS = ["step", "seconds", "loss", "train_psnr", "test_psnr", "lr", "samples_per_ray", "skip_fraction"]


def setup(config: Config, progress: Progress, par: DataParallel | None = None) -> tuple[Loop, Scene, Path, dict]:
    """The run's loop (its config the resolved one), the scene, its path and the manifest's `used.defaults`.
    Data-parallel (`par`): every rank reads the run's files, then rank 0 alone writes config.json."""
    device = resolve_device(config.device) if par is None else par.device
    scene_path, scene = _read_scene(Path(config.scene_dir))
    run_dir = Path(config.run_dir)
    ckpt_path = run_dir / "checkpoint.pt"
    state = read_checkpoint(ckpt_path, device) if config.resume else None
    record = {"scene_sha256": scene_sha256(scene_path)}
    if state is not None:
        config, resumed = resume_config(config, run_dir, scene_path)  # the same run, or one line naming why not
        record["resumed"] = [*_recorded(run_dir).get("resumed", []), {"step": int(state["step"]), **resumed}]
    if par is not None:
        par.barrier()  # every rank has read config.json and the checkpoint before rank 0 rewrites them
    _check_method(config, ckpt_path, state)
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    train_idx, test_idx = scene.split("train"), scene.split("test") or scene.split("val")
    downscale = resolve_downscale(config, scene, train_idx, device)
    train = load_views(scene, train_idx, downscale)
    test = load_views(scene, test_idx, downscale) if test_idx else None
    photos = Photos(scene=scene, train=train, test=test, train_idx=train_idx)
    found = resolve_defaults(config, photos, device, downscale)
    _clear_plain_background(found, train, test)
    resolved = found.config
    if par is not None and resolved.batch_rays < par.world.size:
        raise UserError(f"expected batch_rays >= the number of ranks ({par.world.size}), got {resolved.batch_rays}")
    method = method_named(resolved.method)
    model = method.build(found.context, found.prepared, state)
    if resolved.appearance:
        restored = restore_appearance(state, device) if state is not None else None
        model.appearance = restored or Appearance(len(train_idx)).to(device)
    hooks = method.hooks(found.context, found.prepared, model)
    cameras = _camera_opt(resolved.refine, scene, train_idx, state, device)
    if cameras is not None:
        hooks.append(PoseRefinement(cameras))
    opt, step, seconds_before, lr_factor = _optimizer(method, model, resolved.lr, state, gen)
    metrics = MetricsLog(run_dir / "metrics.csv", METRICS)
    if config.resume:
        metrics.load()
        metrics.rows = [r for r in metrics.rows if int(r["step"]) <= step]
    if par is None or par.writer:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_run_config(run_dir, resolved, scene_path, record)
    loop = Loop(
        config=resolved,
        method=method,
        model=model,
        opt=opt,
        train=train,
        test=test,
        eval_px=_eval_pixels(resolved, test),
        gen=gen,
        device=device,
        metrics=metrics,
        ckpt_path=ckpt_path,
        progress=progress,
        hooks=hooks,
        step=step,
        seconds_before=seconds_before,
        lr_factor=lr_factor,
        parallel=par,
    )
    return loop, scene, scene_path, _record(found, model)


def write_run_config(run_dir: Path, resolved: Config, scene_path: Path, record: dict | None = None) -> None:
    """config.json (module doc) for the resolved Config, with the run's `record` (scene_sha256, resumed); None:
    the record of the config.json already there (the end of the run rewrites what its start wrote)."""
    scene_abs = scene_path.resolve()
    if record is None:
        record = {k: v for k, v in _recorded(run_dir).items() if k in RECORD}
    doc = {
        **config_to_json(dataclasses.replace(resolved, scene_dir=scene_abs)),
        "scene_from_run": scene_from_run(run_dir, scene_abs),
        **record,
    }
    write_json(run_dir / "config.json", doc)


def _recorded(run_dir: Path) -> dict:
    """The run's config.json as it is (empty when there is none or it is unreadable: the caller checked it)."""
    try:
        doc = json.loads((run_dir / "config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _read_scene(scene_path: Path) -> tuple[Path, Scene]:
    if not (scene_path.is_file() or (scene_path / "transforms.json").is_file()):
        raise UserError(f"{scene_path}: no transforms.json (run convert or scene first)")
    return scene_path, read_scene(scene_path)


def _check_method(config: Config, ckpt_path: Path, state: dict | None) -> None:
    """UserError when the checkpoint to resume from was written by another method than the config asks for."""
    if state is not None and (found := method_of_checkpoint(state)) != config.method:
        raise UserError(f"{ckpt_path}: checkpoint holds a {found} run, config asks for method {config.method}")


def _clear_plain_background(found: Defaults, train: Views, test: Views | None) -> None:
    """Auto background on a plain colour: the plain colour's regions that touch the image border become
    transparent in every view; with pose refinement the object's pixels train on a random colour too
    (`Views.mask_colour`'s opaque_object). The share of training pixels joins the background's reason."""
    if found.plain_colour is None:
        return
    refine = found.config.refine is not None
    share = train.mask_colour(found.plain_colour, opaque_object=refine)
    if test is not None:
        test.mask_colour(found.plain_colour)
    found.reasons["background"] += (
        f"; {share:.1%} of the training pixels (the plain colour's regions that touch "
        "the image border) made transparent"
        + (
            "; pose refinement: the object's pixels train on a random colour too (they must be opaque)"
            if refine
            else ""
        )
    )


def _camera_opt(
    refine: RefineOptions | None, scene: Scene, train_idx: tuple[int, ...], state: dict | None, device: torch.device
) -> CameraOpt | None:
    """The training cameras' corrections (restored on resume), or None without pose refinement."""
    if refine is None:
        return None
    poses = np.stack([scene.frames[i].world_from_cam for i in train_idx])
    pivot = pivot_depths(poses, np.asarray(scene.aabb, dtype=np.float64).mean(0))
    cameras = CameraOpt(poses, focal=refine.focal, schedule=CameraSchedule(lr=refine.camera_lr), pivot=pivot)
    cameras = cameras.to(device)
    if state is not None and state.get("camera_opt") is not None:
        cameras.load_dict(state["camera_opt"])
    return cameras


def _optimizer(
    method: Method, model: TrainModel, lr: float, state: dict | None, gen: torch.Generator
) -> tuple[torch.optim.Optimizer, int, float, float]:
    """Adam over the model, and the step, training seconds and learning-rate factor to start from: 0 for a new run,
    the checkpoint's (with the optimiser and the ray generator; the model's weights: `Method.build`) on resume."""
    opt = make_optimizer(model, lr)
    if state is None:
        return opt, 0, 0.0, 1.0
    opt.load_state_dict(method.optimizer_state(state))
    gen.set_state(state["rng"])
    return opt, int(state["step"]), float(state["seconds"]), float(state["lr_factor"])


def _eval_pixels(config: Config, test: Views | None) -> torch.Tensor | None:
    """[K] held-out rays for the periodic test PSNR (None without a test split)."""
    if test is None:
        return None
    g = torch.Generator().manual_seed(config.seed + 1)
    n = test.n_rays  # randperm holds 8 bytes a pixel: above 16 M pixels, draw with replacement instead
    if n <= 1 << 24:
        return torch.randperm(n, generator=g)[: config.eval_pixels]
    return torch.randint(n, (config.eval_pixels,), generator=g)


def _record(found: Defaults, model: TrainModel) -> dict:
    """The manifest's `used.defaults`: each default's reason, and the values the run resolved (the method's options,
    the batch and the background)."""
    resolved = {
        "options": config_to_json(found.config.options),
        "batch_rays": found.config.batch_rays,
        "background": model.background.describe(),
    }
    return {**found.reasons, "resolved": resolved}
