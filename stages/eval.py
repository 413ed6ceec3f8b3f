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

import csv
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from nerfpipe.data.atomic import write_json
from nerfpipe.data.checks import HOLDOUT_FLOOR_DB, HOLDOUT_GAP_DB, Check, verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.ground_truth import GroundTruth, read_ground_truth
from nerfpipe.data.masks import load_masked_image
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, Stopwatch, config_to_json, sidecar, write_manifest
from nerfpipe.data.transforms import Scene
from nerfpipe.model import OPAQUE, load_trained, render_view, resolve_device
from nerfpipe.model.appearance import EVAL_RULES as APPEARANCE_RULES
from nerfpipe.model.appearance import apply_transform, fit_code
from nerfpipe.model.camera_opt import TEST_POSE_OPT_RULE, optimise_test_pose, test_pose_placement
from nerfpipe.model.splat_run import open_input
from nerfpipe.radiance.align import umeyama
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.metrics import psnr

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
]

ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"
"""torchvision's AlexNet checkpoint file name, which lpips loads from the torch hub cache."""
SAME_FRAME_TOL = 1e-4
"""Camera centres within this fraction of the ground-truth extent: the run is already in the GT frame."""
TEST_POSE_STEPS = 100
"""Default `--test-pose-steps` for runs trained with --refine-poses (each step renders 2048 of the photo's pixels)."""
MIN_PSNR = HOLDOUT_FLOOR_DB
"""Self-check: the held-out PSNR (dB) under which the renders are suspect in themselves (`data.checks`)."""
MAX_GAP_DB = HOLDOUT_GAP_DB
"""Self-check: how far (dB) the held-out PSNR may fall under the run's train PSNR (`data.checks`)."""


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
    test_pose_steps: int | None = None
    """Runs trained with --refine-poses: optimise each test camera's pose against its photo for this many steps
    with the field frozen before scoring (NeRF--, BARF, nerfstudio; `model.camera_opt.optimise_test_pose`); 0:
    off, the test cameras are only mapped into the refined frame. None: TEST_POSE_STEPS for refined runs (the
    field learned in its own frame: a test camera placed by the similarity alone is off by the frame's residual
    drift), 0 for the others and for runs whose refinement the guard stopped (they kept the input cameras; on the
    refine benchmark's posed 64 px scene the optimisation moved their test cameras 3.8 deg and cost 0.23 dB)."""
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


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM of two [H, W, 3] images in [0, 1] (skimage defaults: 7x7 uniform window)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0))


def lpips_status() -> tuple[Any | None, str | None]:
    """(an LPIPS-AlexNet callable, None) when the package and every weight file are present offline, else
    (None, reason). Never downloads."""
    try:
        import lpips  # noqa: F401
    except ImportError:
        return None, "the lpips package is not installed (nerfpipe never downloads it or its weights)"
    hub = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS
    lin = Path(lpips.__file__).parent / "weights" / "v0.1" / "alex.pth"
    missing = [str(p) for p in (hub, lin) if not p.is_file()]
    if missing:
        return None, f"LPIPS weights not present offline: {', '.join(missing)} (never downloaded)"
    try:
        model = lpips.LPIPS(net="alex", verbose=False).eval()
    except Exception as exc:  # any failure to build it offline is a reason, not a crash
        return None, f"LPIPS could not be built offline: {type(exc).__name__}: {exc}"

    @torch.no_grad()
    def score(pred: np.ndarray, gt: np.ndarray) -> float:
        def to_t(x):
            return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].float() * 2 - 1

        return float(model(to_t(pred), to_t(gt)).item())

    return score, None


def align_to(scene: Scene, gt: GroundTruth) -> dict[str, Any]:
    """How the run's source frame maps onto the ground-truth frame, from camera centres matched by file name.

    Returns {method: none | similarity, scale (GT units per user unit), matched, rms_centre_error, ...}.
    """
    src, dst = [], []
    for f in scene.frames:
        name = Path(f.file_path).stem
        if name in gt.world_from_cam:
            src.append(scene.source_world_from_cam(f.world_from_cam)[:3, 3])
            dst.append(gt.world_from_cam[name][:3, 3])
    if not src:
        raise UserError(f"--ground-truth: no image name of the run's scene appears in {gt.folder / 'cameras.json'}")
    src_a, dst_a = np.array(src), np.array(dst)
    extent = float(np.linalg.norm(dst_a.max(0) - dst_a.min(0))) or 1.0
    err = np.linalg.norm(src_a - dst_a, axis=1)
    if err.max() <= SAME_FRAME_TOL * extent:
        return {
            "method": "none",
            "reason": "the run's cameras (source frame) coincide with the ground truth",
            "scale": 1.0,
            "matched": len(src),
            "rms_centre_error": float(np.sqrt((err**2).mean())),
        }
    if len(src) < 3:
        raise UserError(f"--ground-truth: frames differ and only {len(src)} camera(s) match by name (need 3)")
    s, rot, t = umeyama(src_a, dst_a)
    res = np.linalg.norm(s * src_a @ rot.T + t - dst_a, axis=1)
    return {
        "method": "similarity",
        "reason": "the run's source frame is not the ground-truth frame: Umeyama fit of camera centres by name",
        "scale": float(s),
        "rotation": rot.tolist(),
        "translation": t.tolist(),
        "matched": len(src),
        "rms_centre_error": float(np.sqrt((res**2).mean())),
    }


def _mean(values: list[float | None]) -> float | None:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else None


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
    downscale = config.downscale or float(trained.run_config.get("downscale") or 1.0)
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
    bg_t = torch.as_tensor(background, dtype=torch.float32, device=device)
    test_pose_moves: list[dict[str, float]] = []
    centre = np.asarray(scene.aabb, dtype=np.float64).mean(0)  # test-pose corrections turn about its depth
    has_appearance = trained.appearance is not None
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
            pose, moved = optimise_test_pose(trained.model, bg_t, pose, intr, photo, pose_steps, centre=centre)
            test_pose_moves.append(moved)
        t0 = time.perf_counter()
        view = _render_scored(trained, intr, pose, device, photo, half, background, depth=gt is not None)
        render_seconds += time.perf_counter() - t0
        rendered_px += w * h
        pred = np.clip(view["rgb"], 0.0, 1.0)
        p_s, g_s = (pred[:, w // 2 :], photo[:, w // 2 :]) if half else (pred, photo)
        row: dict[str, Any] = {
            "name": Path(scene.frames[i].file_path).name,
            "psnr": psnr(p_s, g_s),
            "ssim": ssim(p_s, g_s),
            "lpips": lpips_fn(p_s, g_s) if lpips_fn else None,
        }
        if gt is not None:
            err, n_cov, n_gt = _depth_errors(trained, view, intr, pose, row["name"], gt, alignment, scale, device)
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
        "psnr": _mean([v["psnr"] for v in views]),
        "ssim": _mean([v["ssim"] for v in views]),
        "lpips": _mean([v["lpips"] for v in views]) if lpips_fn else None,
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
    }
    result.update(_depth_summary(gt, alignment, abs_errors, covered, gt_pixels))
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


def train_psnr(run_dir: Path) -> tuple[float, str] | None:
    """The last `train_psnr` in RUN_DIR/metrics.csv and where it comes from, or None (no file, no value)."""
    path = Path(run_dir) / "metrics.csv"
    if not path.is_file():
        return None
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if (r.get("train_psnr") or "").strip()]
    if not rows:
        return None
    try:
        return float(rows[-1]["train_psnr"]), f"{path.name}, step {rows[-1].get('step', '?')}"
    except ValueError:
        return None


def self_checks(psnr_value: float | None, train: tuple[float, str] | None) -> list[Check]:
    """The held-out PSNR against its floor and (when the run has one) against the train PSNR (module doc)."""
    held_out = math.nan if psnr_value is None else float(psnr_value)
    checks = [
        Check.lower(
            "holdout_psnr",
            held_out,
            MIN_PSNR,
            "the renders of the held-out views hardly resemble "
            "the photos: too little training, bad poses or a test split the cameras never saw",
            unit=" dB",
        )
    ]
    if train is not None:
        checks.append(
            Check.upper(
                "holdout_gap",
                train[0] - held_out,
                MAX_GAP_DB,
                f"the held-out views score far under the training views ({train[0]:.1f} dB, {train[1]}): the field "
                "overfitted its photos, or the held-out cameras disagree with the training ones (poses, test split)",
                unit=" dB",
            )
        )
    return checks


def _render_scored(
    trained, intr, pose, device, photo: np.ndarray, half: bool, background: np.ndarray, depth: bool = True
) -> dict:
    """render_view; with the half rule and appearance codes, the view rendered without appearance, its code
    fitted on the left half of `photo` [H, W, 3] (`model.appearance.fit_code`) and its transform applied."""
    app = trained.appearance
    if not half or app is None:
        return render_view(trained, intr, pose, device, depth=depth)
    with trained.appearance_off():
        view = render_view(trained, intr, pose, device)
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


def _depth_errors(trained, view, intr, pose, name, gt, alignment, scale, device):
    """|pred - gt| [n] in GT units on the pixels where the GT has depth; (None, 0, 0) when no GT depth file."""
    path = gt.folder / "depth" / f"{Path(name).stem}.npy"
    if not path.is_file():
        return None, 0, 0
    gt_depth = np.load(path, allow_pickle=False).astype(np.float64)
    if gt_depth.shape != view["depth"].shape:  # ground truth at another resolution: render at its size
        view = render_view(trained, intr.scaled(gt_depth.shape[1] / intr.w), pose, device)
    pred = view["depth"].astype(np.float64) / scale * alignment["scale"]
    has_gt = np.isfinite(gt_depth) & (gt_depth > 0)
    ok = has_gt & np.isfinite(pred)
    covered = int((has_gt & (view["acc"] >= OPAQUE)).sum())
    return np.abs(pred[ok] - gt_depth[ok]), covered, int(has_gt.sum())


def _depth_summary(gt, alignment, abs_errors, covered, gt_pixels) -> dict[str, Any]:
    if gt is None:
        return {
            "depth_mae": None,
            "depth_median_abs_error": None,
            "depth_coverage": None,
            "depth_alignment": None,
            "depth_unavailable": "no --ground-truth given",
            "ground_truth": None,
        }
    err = np.concatenate(abs_errors) if abs_errors else np.zeros(0)
    return {
        "depth_mae": float(err.mean()) if err.size else None,
        "depth_median_abs_error": float(np.median(err)) if err.size else None,
        "depth_coverage": covered / gt_pixels if gt_pixels else None,
        "depth_units": "ground-truth units (metres): run depth / applied_scale x alignment scale",
        "depth_pixels": int(err.size),
        "depth_alignment": alignment,
        "depth_unavailable": None if err.size else "no ground-truth depth file matched a test view",
        "ground_truth": str(gt.folder),
    }
