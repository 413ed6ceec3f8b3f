"""`train` stage: fit a method's model (`--method`, `model.methods`: a radiance field by default) to a posed scene
(`transforms.json`) and write a run directory.

Run directory (docs/DESIGN.md "Trained run directory"):
  config.json, checkpoint.pt (`model.checkpoint`: tensors and primitive containers only, loads with
  weights_only=True), metrics.csv (step, seconds, loss, train_psnr, test_psnr (blank when not evaluated), lr,
  samples_per_ray, skip_fraction), psnr_vs_time.png, manifest.json (written last).

Reruns and reliability (docs/RELIABILITY.md): the run folder is locked while train writes there
(`data.lock`); a folder holding a run (checkpoint.pt or manifest.json) is refused unless `--resume` (continue:
the manifest is removed until the run ends again) or `--overwrite` (the old run goes to RUN_DIR.previous/, deleted
when the new run succeeds). Ctrl-C or SIGTERM saves a checkpoint at the current step and exits 130/143 with one
line; a checkpoint is also written every `checkpoint_seconds`. The manifest records the checkpoint's sha256.

The story: `validate` checks the config alone (`stages.train.config`) before anything is read, `setup` reads the
scene, resolves the defaults (`stages.train.defaults`, in one place: config.json records the result) and builds (or
resumes) the method's model and its hooks (`stages.train.setup`, `model.methods`), `Loop.run` optimises it
(`stages.train.loop`), `_final_eval` renders evenly spaced test views in full, and the manifest records what was
used and left out (`stages.train.report`).

Data-parallel (`model.distributed`): under torchrun (`torchrun --nproc-per-node N -m nerfpipe.cli train ...`) the
N ranks share each step's rays and average their gradients; rank 0 takes the run folder (lock, resume and
overwrite rules) and tells the others whether it could, writes every file, and alone renders the final evaluation
and the reports; the manifest's `used.world_size` records N. Without torchrun nothing of this runs.

Conventions: rays in the scene frame, unit directions, t = Euclidean distance (radiance.camera).
Training draws random rays across all train views (colours held as uint8, rays made per batch from each view's
camera; `model.views`). RGBA scenes composite a random background per ray during training and white for
evaluation. Methods: `density` (TensoRF VM, occupancy-grid marching, coarse-to-fine upsampling; the default) and
`nerf` (the NeRF paper: 64 stratified + 128 importance samples, coarse and fine networks); others register
(`model.methods.registry`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.checks import verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import output_folder, write_manifest
from nerfpipe.data.stop import stop_on_signals
from nerfpipe.data.transforms import Scene
from nerfpipe.model.appearance import EVAL_RULE as APPEARANCE_EVAL_RULE
from nerfpipe.model.camera_opt import pose_report, write_refined_transforms
from nerfpipe.model.device import cpu_threads
from nerfpipe.model.distributed import DataParallel, joined, rank_device, world_from_env
from nerfpipe.model.views import evenly_spaced
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.stages.train.checks import train_checks
from nerfpipe.stages.train.config import Config, RefineOptions, validate
from nerfpipe.stages.train.defaults import final_eval_stride
from nerfpipe.stages.train.fog import seen_occupied_share
from nerfpipe.stages.train.loop import Loop, TrainingDiverged, evaluate_psnr
from nerfpipe.stages.train.refine import PoseRefinement
from nerfpipe.stages.train.report import per_view_report, plot_psnr, used_and_left_out
from nerfpipe.stages.train.setup import setup, write_run_config

__all__ = ["Config", "RefineOptions", "Outputs", "run", "TrainingDiverged", "evenly_spaced"]

VERSION = "1"


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
    """Mean PSNR over the test views scored at the end (None when the scene has no test split)."""
    test_scored: str = ""
    """What test_psnr scored, in words: "7 of 7 test views, every 3rd pixel" ("" without a test split)."""


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Train a field on config.scene_dir into config.run_dir (see the module docstring).

    progress: the CLI's display (`data.progress`); None trains silently.
    """
    validate(config)
    world = world_from_env()
    if world.size > 1:
        with joined(world, rank_device(config.device, world)) as par, _folder(config, par):
            with cpu_threads(config.threads):
                return _run(config, (progress or NO_PROGRESS) if par.writer else NO_PROGRESS, par)
    marks = ("checkpoint.pt", "manifest.json")
    with output_folder(config.run_dir, overwrite=config.overwrite, resume=config.resume, marks=marks):
        with cpu_threads(config.threads):
            return _run(config, progress or NO_PROGRESS)


@contextlib.contextmanager
def _folder(config: Config, par: DataParallel) -> Iterator[None]:
    """Data-parallel: rank 0 takes the run folder (`output_folder`) and tells the other ranks whether it could;
    they stop with one line when it could not (rank 0 prints why)."""
    if not par.writer:
        if not par.announce():
            raise UserError(f"{config.run_dir}: rank 0 could not take the run folder (its message says why)")
        yield
        return
    taken = False
    try:
        with output_folder(
            config.run_dir, overwrite=config.overwrite, resume=config.resume, marks=("checkpoint.pt", "manifest.json")
        ):
            taken = True
            par.announce(True)
            yield
    finally:
        if not taken:
            par.announce(False)


def _run(config: Config, progress: Progress, par: DataParallel | None = None) -> Outputs:
    started = time.time()
    loop, scene, scene_path, record = setup(config, progress, par)
    config = loop.config
    run_dir = Path(config.run_dir)
    if par is None or par.writer:
        (run_dir / "manifest.json").unlink(missing_ok=True)  # resumed: not a finished run until the end
    with stop_on_signals() as stop:  # the loop checkpoints and raises Interrupted on SIGINT/SIGTERM
        loop.stop = stop
        seconds = loop.run()
    if par is not None and not par.writer:  # rank 0 evaluates and writes the rest
        return Outputs(
            run_dir=run_dir,
            checkpoint=loop.ckpt_path,
            metrics=loop.metrics.path,
            plot=run_dir / "psnr_vs_time.png",
            manifest=run_dir / "manifest.json",
            steps=loop.step,
            seconds=seconds,
            test_psnr=None,
        )
    test_psnr, chosen, n_views, stride = _final_eval(config, loop, seconds)
    write_run_config(run_dir, dataclasses.replace(config, final_eval_views=n_views), scene_path)
    plot = run_dir / "psnr_vs_time.png"
    plot_psnr(plot, loop.metrics.rows, f"train {config.method} on {scene_path.name}")
    train_idx, test_idx = scene.split("train"), scene.split("test") or scene.split("val")
    used, left_out = used_and_left_out(
        scene=scene,
        loop=loop,
        seconds=seconds,
        train_idx=train_idx,
        test_idx=test_idx,
        chosen=chosen,
        stride=stride,
        test_psnr=test_psnr,
    )
    used["defaults"] = record
    outputs = [run_dir / n for n in ("config.json", "checkpoint.pt", "metrics.csv", "psnr_vs_time.png")]
    used["per_view"], depths = per_view_report(
        run_dir, loop.model, scene, train_idx, config.downscale, seconds, loop.eval_rays_per_second, loop.device
    )
    outputs += [run_dir / f for f in used["per_view"]["files"]]
    outputs += _refinement_records(loop, scene, train_idx, used, left_out)
    described = loop.model.describe()
    skip = described.get("occupancy_skip_fraction")
    space = loop.model.space
    grid = getattr(loop.model, "grid", None)
    boxed = isinstance(grid, OccupancyGrid) and space is not None and space.object_box
    seen = seen_occupied_share(grid, loop.model.field.density, depths) if boxed else None
    checks = train_checks(
        rows=loop.metrics.rows,
        test_psnr=test_psnr,
        per_view=used["per_view"],
        occupied=None if skip is None else 1.0 - skip,
        object_box=space.object_box if space is not None else False,
        pose=used.get("pose_refinement"),
        scene_dir=scene_path if scene_path.is_dir() else None,
        seen_occupied=seen,
        background_conflict=record.get("background_conflict"),
    )
    checks += loop.method.checks(loop.model)
    inputs = [scene_path / "transforms.json"] if scene_path.is_dir() else [scene_path]
    manifest = write_manifest(
        run_dir,
        stage="train",
        started=started,
        inputs=inputs,
        outputs=outputs,
        used=used,
        left_out=left_out,
        version=VERSION,
        checkpoint_sha256=loop.ckpt_sha256,
        **verdict(checks),
    )
    return Outputs(
        run_dir=run_dir,
        checkpoint=loop.ckpt_path,
        metrics=loop.metrics.path,
        plot=plot,
        manifest=manifest,
        steps=loop.step,
        seconds=seconds,
        test_psnr=test_psnr,
        test_scored=used.get("test_psnr_scored", {}).get("words", ""),
    )


def _refinement_records(loop: Loop, scene: Scene, train_idx: tuple[int, ...], used: dict, left_out: dict) -> list:
    """Pose refinement and appearance in the manifest; the refined cameras' transforms.json (its path, or [])."""
    if loop.model.appearance is not None:
        used["appearance"] = {
            "codes": loop.model.appearance.n_views,
            "dim": loop.model.appearance.dim,
            "evaluation": APPEARANCE_EVAL_RULE,
        }
    else:
        left_out["appearance"] = "off (train --appearance): every image is assumed to share one appearance"
    refine = next((h for h in loop.hooks if isinstance(h, PoseRefinement)), None)
    if refine is None:
        left_out["pose_refinement"] = "off (train --refine-poses): the input cameras are taken as exact"
        return []
    used["pose_refinement"] = pose_report(refine.cameras, scene, train_idx)
    path = Path(loop.config.run_dir) / "transforms.json"
    return [write_refined_transforms(scene, refine.cameras.to_dict(), train_idx, path)]


def _final_eval(config: Config, loop: Loop, seconds: float) -> tuple[float | None, list[int], int, int]:
    """Mean PSNR over the test views (None without a test split), the views scored, final_eval_views resolved for
    config.json, and the pixel stride. final_eval_views given: that many evenly spaced views, whole. Else every test
    view on every stride-th pixel, the stride `stages.train.defaults.final_eval_stride` fits in the budget at the
    render speed of the periodic evaluations (or of a few rays). The PSNR is logged to metrics.csv."""
    loop.model.train_mode(False)
    test_psnr, chosen, stride = None, [], 1
    if loop.test is not None:
        n = len(loop.test.shapes)
        bg = loop.model.background.eval_colour().detach()
        if config.final_eval_views is not None:
            chosen = evenly_spaced(n, config.final_eval_views)
        else:
            chosen = list(range(n))
            rate = loop.eval_rays_per_second or _rays_per_second(loop, bg)
            stride = final_eval_stride(config, n, rate, float(np.mean([h * w for h, w in loop.test.shapes])))
        rays = loop.test_rays()
        psnrs = [
            evaluate_psnr(loop.model, loop.test, loop.test.pixels_of(v)[::stride], bg, loop.device, rays)
            for v in chosen
        ]
        test_psnr = float(np.mean(psnrs))
        loop.metrics.append(step=loop.step, seconds=round(seconds, 3), test_psnr=f"{test_psnr:.3f}")
    loop.metrics.save()
    return test_psnr, chosen, len(chosen), stride


def _rays_per_second(loop: Loop, bg: torch.Tensor) -> float:
    idx = torch.arange(min(4096, loop.test.n_rays))
    t0 = time.perf_counter()
    evaluate_psnr(loop.model, loop.test, idx, bg, loop.device)
    return idx.numel() / max(time.perf_counter() - t0, 1e-6)
