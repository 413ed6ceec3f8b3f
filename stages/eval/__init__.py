"""Stage `eval`: image quality on the held-out views, render speed and (with ground truth) depth error.

    nerfpipe eval RUN_DIR|SPLATS.ply OUT.json [--ground-truth DIR]

Per test view (the `test` split; `val` when there is none): PSNR, SSIM (`skimage.metrics.structural_similarity`,
channel_axis, data_range 1) of the render against the photo (RGBA photos composited on the run's evaluation
background), at the photo's resolution. Rays per second = rendered pixels / render seconds (all views).
LPIPS only when the `lpips` package and its AlexNet weights are already on this machine (never downloaded);
otherwise `"lpips": null` with the reason in `"lpips_unavailable"`.

Depth (with `--ground-truth`, the synthetic scene's `ground_truth/` folder or the scene folder holding it):
`cameras.json` with `frames: {image name or stem: world_from_cam | {world_from_cam, ...}}` and
`depth/<image stem>.npy` z-depth in metres, 0 = background. The run's expected z-depth is taken to the user's
(source) units (/ applied_scale) and compared on the pixels where the ground truth has depth. When the run's
cameras, mapped to the source frame, do not coincide with the ground-truth cameras (e.g. COLMAP poses), a
similarity (Umeyama) fitted from the run's camera centres to the ground-truth centres, matched by image stem,
converts the depth scale; the JSON says which (`depth_alignment.method`: none | similarity).

Runs trained with `--refine-poses` are scored from the refined frame: the test cameras are mapped into it by the
similarity from the input training cameras to the refined ones (`model.camera_opt`), then each is optimised against
its photo with the field frozen (`--test-pose-steps`, TEST_POSE_STEPS by default; JSON `test_poses`). Runs
trained with `--appearance` render with the mean appearance code (`--appearance-rule mean`, the default), or with
NeRF-W's protocol (`--appearance-rule half`): each test view's code is fitted to the left half of its photo and
the view is scored on the right half only -- runs without appearance are then scored on the right half too, so
the two compare on the same pixels (JSON `appearance`, `appearance_rule`, `scored_pixels`).

A splat .ply from `nerfpipe splat` is scored on its run's test views, rasterised (`model.splat_run`; its train PSNR
is the splat report's); `input` in OUT.json and the manifest's `used` says which (field | splats, the file's sha256).
Writes OUT.json, OUT.metrics.csv (per view: step, seconds, psnr, ssim, depth_mae) and OUT.manifest.json (last).

Self-check (`check`: ok | suspect and `checks` (`data.checks`), in OUT.manifest.json and OUT.json):
- `holdout_psnr`: the mean held-out PSNR, at least `MIN_PSNR` dB. Under it a render is hardly the photo whatever
  the cause (too little training, wrong poses, a test split the cameras never saw).
- `holdout_gap`: the run's train PSNR minus the held-out PSNR, at most `MAX_GAP_DB` dB. The train PSNR is the last
  `train_psnr` of the run's metrics.csv (the training batches' colour loss over the last logging interval, at the
  training resolution: what the field fits); OUT.json's `train_psnr` / `train_psnr_from` say which row. A field
  that explains its training photos far better than photos it did not see has overfitted them (too few or too
  similar views), or the held-out cameras disagree with the training ones (bad poses, a wrong test split). Left out
  when the run has no train PSNR.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from nerfpipe.data.atomic import write_json
from nerfpipe.data.checks import verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.ground_truth import GroundTruth, read_ground_truth
from nerfpipe.data.masks import load_masked_image
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, Stopwatch, config_to_json, sidecar, write_manifest
from nerfpipe.model import load_trained, render_view, require, resolve_device
from nerfpipe.model.appearance import EVAL_RULES as APPEARANCE_RULES
from nerfpipe.model.appearance import apply_transform, fit_code
from nerfpipe.model.camera_opt import TEST_POSE_OPT_RULE, optimise_test_pose, test_pose_placement
from nerfpipe.model.field_model import inference, inference_record
from nerfpipe.model.splat_run import open_input
from nerfpipe.model.view_cache import KEPT, open_view_cache
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.metrics import psnr
from nerfpipe.stages.eval.checks import MAX_GAP_DB, MIN_PSNR, self_checks, train_psnr
from nerfpipe.stages.eval.depth_error import align_to, depth_errors, depth_summary
from nerfpipe.stages.eval.metrics import lpips_status, mean_of, ssim

__all__ = [
    "Config",
    "Outputs",
    "run",
    "ssim",
    "lpips_status",
    "GroundTruth",
    "read_ground_truth",
    "align_to",
    "train_psnr",
    "self_checks",
    "MIN_PSNR",
    "MAX_GAP_DB",
    "TEST_POSE_STEPS",
]

TEST_POSE_STEPS = 100
"""Default `--test-pose-steps` for runs trained with --refine-poses (each step renders 2048 of the photo's pixels)."""


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory, or a splat .ply made from one by `nerfpipe splat` (scored on the run's test views)."""
    out: Path
    """Output JSON file."""
    views: int | None = None
    """Score this many test views, evenly spaced over the split (None: all of them)."""
    downscale: float | None = None
    """Evaluate on the photos shrunk by this factor (area filter). None: the factor the run trained at
    (train's downscale; 1 for runs that kept full-size images). `eval --downscale 1` scores full size."""
    ground_truth: Path | None = None
    """Ground-truth folder (cameras.json, depth/*.npy in metres) or the scene folder holding ground_truth/."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    exact: bool = False
    """Score renders whose rays stop at float32's epsilon of light with every sample coloured
    (`model.field_model.EXACT`); default: `FAST` (faster, a few hundredths of a dB apart: docs/TRAINING.md
    "Inference"). eval.json's `inference` says which."""
    test_pose_steps: int | None = None
    """Runs trained with --refine-poses: optimise each test camera's pose against its photo for this many steps
    with the field frozen before scoring (NeRF--, BARF, nerfstudio; `model.camera_opt.optimise_test_pose`); 0:
    off, the test cameras are only mapped into the refined frame. None: TEST_POSE_STEPS for refined runs (the
    field learned in its own frame: a test camera placed by the similarity alone is off by the frame's residual
    drift), 0 for the others and for runs whose refinement the guard stopped (they kept the input cameras; moving
    their test cameras cost PSNR: docs/MEASUREMENTS.md, "Pose refinement")."""
    appearance_rule: Literal["mean", "half"] = "mean"
    """Runs with --appearance: mean (render with the mean code, score whole views) or half (NeRF-W: fit each test
    view's code on the left half of its photo, score the right half; every run is then scored on right halves)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out: Path
    """The JSON report."""
    metrics: Path
    manifest: Path
    result: dict
    """What OUT.json holds."""


def run(config: Config, progress: Progress | None = None) -> Outputs:
    started = time.time()
    out = Path(config.out)
    if out.suffix.lower() != ".json":
        raise UserError(f"{out}: expected a .json output path")
    source = open_input(config.run_dir)
    source.refuse_output(out, "eval output")
    gt = read_ground_truth(config.ground_truth) if config.ground_truth is not None else None
    device = resolve_device(config.device)
    trained = source.load(device, load_trained)
    scene = trained.scene
    split = "test" if scene.split("test") else "val"
    idx = scene.split(split)
    if not idx:
        raise UserError(f"{config.run_dir}: the run's scene has no test or val split to evaluate on")
    if config.views is not None:
        if config.views < 1:
            raise UserError(f"--views: expected >= 1, got {config.views}")
        idx = tuple(idx[k] for k in sorted({round(float(v)) for v in np.linspace(0, len(idx) - 1, config.views)}))
    alignment = align_to(scene, gt) if gt is not None else None
    lpips_fn, lpips_reason = lpips_status()
    background = trained.background.detach().float().cpu().numpy().reshape(3)
    scale = float(scene.applied_scale)

    metrics = MetricsLog(sidecar(out, "metrics.csv"), ["step", "seconds", "psnr", "ssim", "depth_mae"])
    clock = Stopwatch()
    views: list[dict[str, Any]] = []
    render_seconds, rendered_px = 0.0, 0
    abs_errors: list[np.ndarray] = []
    covered = gt_pixels = 0
    progress = progress or NO_PROGRESS
    task = progress.add_task(f"eval {split}", total=len(idx))
    if config.downscale is not None and not config.downscale >= 1:
        raise UserError(f"--downscale: expected >= 1, got {config.downscale}")
    downscale = config.downscale or trained.downscale
    if config.appearance_rule not in APPEARANCE_RULES:
        raise UserError(
            f"--appearance-rule: expected one of {', '.join(APPEARANCE_RULES)}, got {config.appearance_rule!r}"
        )
    half = config.appearance_rule == "half"
    if config.test_pose_steps is not None and config.test_pose_steps < 0:
        raise UserError(f"--test-pose-steps: expected >= 0, got {config.test_pose_steps}")
    refinement = trained.pose_refinement
    moved = refinement is not None and refinement.get("stopped_at_step") is None  # stopped: the input cameras kept
    asked = config.test_pose_steps
    pose_steps = 0 if refinement is None else (TEST_POSE_STEPS if moved else 0) if asked is None else asked
    if pose_steps:
        require(trained, "pose_opt", stage="eval (placing test cameras of a run with refined poses)")
    bg_t = torch.as_tensor(background, dtype=torch.float32, device=device)
    test_pose_moves: list[dict[str, float]] = []
    centre = np.asarray(scene.aabb, dtype=np.float64).mean(0)  # test-pose corrections turn about its depth
    has_appearance = trained.appearance is not None
    cache = open_view_cache(Path(source.run_dir)) if source.splat_file is None else None
    infer = inference(config.exact)
    kept = 0  # views whose depth went into the run's render cache (model.view_cache) for `depth`
    for k, i in enumerate(idx):
        photo = load_masked_image(scene, i)  # masked-out pixels transparent, as in training (data.masks)
        if downscale != 1.0:
            import cv2

            small = scene.frame_intrinsics(i).scaled(1.0 / downscale)
            photo = cv2.resize(photo, (small.w, small.h), interpolation=cv2.INTER_AREA)
        if photo.shape[2] == 4:
            photo = over_background(photo[..., :3], photo[..., 3:], background)
        intr = scene.frame_intrinsics(i)
        h, w = photo.shape[:2]
        if (intr.w, intr.h) != (w, h):
            intr = intr.scaled(w / intr.w)
        pose = scene.frames[i].world_from_cam
        if pose_steps:
            pose, moved = optimise_test_pose(trained, bg_t, pose, intr, photo, pose_steps, centre=centre)
            test_pose_moves.append(moved)
        t0 = time.perf_counter()
        view = _render_scored(trained, intr, pose, device, photo, half, background, gt is not None, infer)
        render_seconds += time.perf_counter() - t0
        rendered_px += w * h
        if cache is not None and not pose_steps and all(key in view for key in KEPT):
            kept += cache.put(intr, pose, view, infer)
        pred = np.clip(view["rgb"], 0.0, 1.0)
        p_s, g_s = (pred[:, w // 2 :], photo[:, w // 2 :]) if half else (pred, photo)
        row: dict[str, Any] = {
            "name": Path(scene.frames[i].file_path).name,
            "psnr": psnr(p_s, g_s),
            "ssim": ssim(p_s, g_s),
            "lpips": lpips_fn(p_s, g_s) if lpips_fn else None,
        }
        if gt is not None:
            err, n_cov, n_gt = depth_errors(trained, view, intr, pose, row["name"], gt, alignment, scale, device)
            if err is not None:
                abs_errors.append(err)
                covered, gt_pixels = covered + n_cov, gt_pixels + n_gt
                row["depth_mae"] = float(err.mean()) if err.size else None
        views.append(row)
        metrics.append(
            step=k,
            seconds=round(clock(), 4),
            psnr=round(row["psnr"], 4),
            ssim=round(row["ssim"], 5),
            depth_mae="" if row.get("depth_mae") is None else round(row["depth_mae"], 6),
        )
        progress.advance(task)

    result: dict[str, Any] = {
        "run_dir": str(source.run_dir),
        "input": source.record(),
        "split": split,
        "n_views": len(views),
        "psnr": mean_of([v["psnr"] for v in views]),
        "ssim": mean_of([v["ssim"] for v in views]),
        "lpips": mean_of([v["lpips"] for v in views]) if lpips_fn else None,
        "lpips_unavailable": lpips_reason,
        "rays_per_second": rendered_px / max(render_seconds, 1e-9),
        "render_seconds": render_seconds,
        "device": str(device),
        "downscale": downscale,
        "views": views,
        "test_poses": TEST_POSE_OPT_RULE if pose_steps else test_pose_placement(refinement),
        "test_pose_optimisation": {
            "steps": pose_steps,
            "median_rotation_deg": float(np.median([m["rotation_deg"] for m in test_pose_moves])),
            "median_translation": float(np.median([m["translation"] for m in test_pose_moves])),
        }
        if test_pose_moves
        else None,
        "appearance": APPEARANCE_RULES[config.appearance_rule] if has_appearance else None,
        "appearance_rule": config.appearance_rule,
        "scored_pixels": "right half of each test view (--appearance-rule half)" if half else "whole views",
        "inference": inference_record(infer),
    }
    result.update(depth_summary(gt, alignment, abs_errors, covered, gt_pixels))
    train = train_psnr(source.run_dir) if source.splat_file is None else source.train_psnr
    result["train_psnr"], result["train_psnr_from"] = train if train is not None else (None, "no metrics.csv value")
    checked = verdict(self_checks(result["psnr"], train))
    result.update(checked)
    metrics.save()
    manifest = write_manifest(
        out.parent,
        stage="eval",
        started=started,
        name=sidecar(out, "manifest.json").name,
        inputs=[*source.inputs, *([gt.folder / "cameras.json"] if gt else [])],
        outputs=[out, metrics.path],
        used={
            "input": result["input"],
            "split": split,
            "views": len(views),
            "device": str(device),
            "appearance_rule": config.appearance_rule,
            "ssim": "skimage structural_similarity, 7x7, data_range 1",
            "test_poses": result["test_poses"],
            "appearance": result["appearance"],
            "render_cache": _cache_record(cache, kept, len(views)),
        },
        left_out={
            **({"lpips": lpips_reason} if lpips_reason else {}),
            **({} if gt else {"depth": "no --ground-truth given"}),
        },
        config=config_to_json(config),
        **checked,
    )
    write_json(out, result)  # last: OUT (make's target) appears only after its manifest, so a failure leaves none
    return Outputs(out=out, metrics=metrics.path, manifest=manifest, result=result)


def _cache_record(cache, kept: int, views: int) -> str:
    """What the run's render cache received (`model.view_cache`: `depth` reads it instead of rendering again)."""
    if cache is None:
        return "none: not a train run folder with a finished manifest"
    if kept < views:
        return f"{kept} of {views} views kept in {cache.folder} (test-pose optimisation, or the folder is read-only)"
    return f"{kept} views' depth kept in {cache.folder} for `depth`"


def _render_scored(
    trained, intr, pose, device, photo: np.ndarray, half: bool, background: np.ndarray, depth: bool, infer
) -> dict:
    """render_view; with the half rule and appearance codes, the view rendered without appearance, its code
    fitted on the left half of `photo` [H, W, 3] (`model.appearance.fit_code`) and its transform applied."""
    app = trained.appearance
    if not half or app is None:
        return render_view(trained, intr, pose, device, depth=depth, infer=infer)
    with trained.appearance_off():
        view = render_view(trained, intr, pose, device, infer=infer)
    h, w = view["acc"].shape
    rgb = torch.from_numpy(view["rgb"]).reshape(-1, 3).to(device)
    acc = torch.from_numpy(view["acc"]).reshape(-1).to(device)
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    left = torch.zeros(h, w, dtype=torch.bool)
    left[:, : w // 2] = True
    left = left.reshape(-1).to(device)
    target = torch.from_numpy(np.ascontiguousarray(photo, dtype=np.float32)).reshape(-1, 3).to(device)
    code = fit_code(app, rgb[left], acc[left], bg, target[left])
    with torch.no_grad():
        out = apply_transform(app.code_transform(code[None]), rgb, acc, bg)
    return {**view, "rgb": out.reshape(h, w, 3).float().cpu().numpy()}
