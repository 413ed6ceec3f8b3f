"""The poses stage's bookkeeping: run state, registration checks, phase timer, poses_report.json, summary.

`RunState` collects what one run saw (copies, screening, timings, the attempts, SfM statistics and the
chosen model: those of the attempt being run, then of the attempt kept);
`build_report` turns it into poses_report.json (also written on failure; with the written model's checks from
`quality`, the EXIF focal prior and why the kept attempt won); `check_features` and
`check_registered` turn too few textured or registered images into one-line UserErrors that say why.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pycolmap
from rich.console import Console
from rich.progress import Progress

from nerfpipe.data.checks import Check, check_line, verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.rundir import MetricsLog, config_to_json
from nerfpipe.stages.poses.colmap import DatabaseStats
from nerfpipe.stages.poses.exif import FocalPrior
from nerfpipe.stages.poses.images import Screen

if TYPE_CHECKING:
    from nerfpipe.stages.poses.config import Config

__all__ = [
    "MIN_REGISTERED",
    "FAIL_FRACTION",
    "WARN_FRACTION",
    "MIN_FEATURES",
    "RunState",
    "PhaseTimer",
    "textured",
    "check_features",
    "check_registered",
    "build_report",
    "print_summary",
    "focal_prior_record",
]

MIN_REGISTERED = 3
FAIL_FRACTION = 0.4
"""Fewer registered images than this fraction is an error (no model is written)."""
WARN_FRACTION = 0.8
"""Fewer registered images than this fraction prints a warning, after retrying with other settings."""
MIN_FEATURES = 100
"""An image with fewer SIFT features than this is reported as texture-less."""


@dataclass(kw_only=True)
class RunState:
    """Mutable state of one run, turned into poses_report.json."""

    started: float
    source: str = ""
    names: dict[str, str] = field(default_factory=dict)  # copy name -> original
    skipped: dict[str, str] = field(default_factory=dict)  # original name -> why (undecodable, dropped)
    screens: dict[str, Screen] = field(default_factory=dict)
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)  # copy name -> (w, h)
    duplicates: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    video: dict[str, Any] | None = None
    stats: DatabaseStats | None = None
    models: list[int] = field(default_factory=list)  # registered images per model found
    model: pycolmap.Reconstruction | None = None
    all_models: dict[int, pycolmap.Reconstruction] = field(default_factory=dict)
    principal_point: str = ""
    radial_term: str = ""  # stages.poses.lens.add_radial_term's verdict ("" when not tried)
    working_size: dict[str, Any] = field(default_factory=dict)  # how the SIFT working size was chosen
    attempts: list[dict[str, Any]] = field(default_factory=list)  # one record per attempt (stages.poses.attempts)
    masks: dict[str, str] = field(default_factory=dict)  # copy name -> its mask file (poses --masks)
    stationary: dict[str, Any] = field(default_factory=dict)  # check_static_matches' figures
    exif_focal: dict[str, FocalPrior] = field(default_factory=dict)  # copy name -> its photo's EXIF focal prior
    focal_prior: dict[int, dict[str, Any]] = field(default_factory=dict)  # camera id -> prior (exif.apply_...)
    checks: list[Check] | None = None  # stages.poses.quality's checks of the model written; None: no model
    choice: str = ""  # why the kept attempt won (stages.poses.choice)
    consistency: tuple[list[Check], dict[str, Any] | None] = field(default_factory=lambda: ([], None))
    """The kept model's consistency checks and their record (stages.poses.consistency)."""
    ladder: dict[str, Any] = field(default_factory=dict)  # why the retry ladder stopped, its time budget


def textured(stats: DatabaseStats) -> bool:
    """Enough images with MIN_FEATURES+ features that a model is possible at all."""
    return sum(k >= MIN_FEATURES for k in stats.features.values()) >= MIN_REGISTERED


def check_features(stats: DatabaseStats) -> None:
    if not textured(stats):
        n = sum(k >= MIN_FEATURES for k in stats.features.values())
        raise UserError(
            f"only {n} of {len(stats.features)} images have {MIN_FEATURES}+ SIFT features: the images "
            "look blank or texture-less; photograph a scene with visible texture (not plain walls, sky or blur)"
        )


def check_registered(state: RunState, matcher: str) -> None:
    total = len(state.stats.features)
    reg = state.model.num_reg_images() if state.model is not None else 0
    if reg < MIN_REGISTERED or reg < FAIL_FRACTION * total:
        few = sum(k < MIN_FEATURES for k in state.stats.features.values())
        unmatched = sum(p == 0 for p in state.stats.verified_pairs.values())
        if few > total // 2:
            cause = f"{few} images have under {MIN_FEATURES} features (texture-less or blurry)"
        elif unmatched > total // 2:
            cause = f"{unmatched} images share no verified matches (too little overlap between views)"
        elif len(state.models) > 1:
            cause = f"the scene split into {len(state.models)} separate models {state.models}"
        else:
            cause = "the views could not be chained together"
        also = "; or try matcher=exhaustive" if matcher != "exhaustive" else ""
        if len(state.attempts) < 2:
            also += "; or allow retries (max_attempts) or a larger max_image_size / max_num_features"
        raise UserError(
            f"only {reg} of {total} images registered{attempts_line(state.attempts)}: {cause}; take more "
            f"overlapping photos (60-80% overlap, small steps around the subject){also}"
        )
    if reg < WARN_FRACTION * total:
        state.warnings.append(f"only {reg} of {total} images registered; see poses_report.json for why")


def attempts_line(attempts: list[dict[str, Any]]) -> str:
    """' (tried as configured 11/22, more features 15/22; kept more features)'; '' after a single attempt."""
    if len(attempts) < 2:
        return ""
    tried = ", ".join(f"{a['name']} {a['registered']}/{a['total']}" for a in attempts)
    kept = [a["name"] for a in attempts if a["kept"]]
    return f" (tried {tried}; kept {kept[0] if kept else 'none'})"


def _why_not_registered(name: str, stats: DatabaseStats, models: dict[int, pycolmap.Reconstruction]) -> str:
    if stats.features.get(name, 0) < MIN_FEATURES:
        return f"few features ({stats.features.get(name, 0)}): blank, blurry or texture-less"
    if stats.verified_pairs.get(name, 0) == 0:
        return "no verified matches with any other image (no overlap?)"
    for rec in models.values():
        if rec.find_image_with_name(name) is not None and rec.find_image_with_name(name).has_pose:
            return f"registered only in a smaller, separate model ({rec.num_reg_images()} images)"
    return f"matched ({stats.verified_pairs[name]} verified pairs) but the mapper could not register it"


def _per_image(state: RunState) -> dict[str, Any]:
    rec, stats = state.model, state.stats
    per_image: dict[str, Any] = {}
    for name, original in state.names.items():
        entry: dict[str, Any] = {"original": original}
        if name in state.skipped:
            entry["left_out"] = state.skipped[name]
        if name in state.sizes:
            entry["size"] = list(state.sizes[name])
        sc = state.screens.get(name)
        if sc is not None:
            entry.update(
                blur=round(sc.blur, 2),
                overexposed=round(sc.overexposed, 4),
                underexposed=round(sc.underexposed, 4),
                flags=sc.flags(),
            )
        if name in state.duplicates:
            entry["near_duplicate_of"] = state.duplicates[name]
        prior = state.exif_focal.get(name)
        entry["exif_focal"] = (
            "absent"
            if prior is None
            else {
                "focal_px": round(prior.focal_px, 2),
                "source": prior.source,
                **({"weak": prior.weak} if prior.weak else {}),
            }
        )
        if stats is not None and name in stats.features:
            entry.update(
                features=stats.features[name], verified_pairs=stats.verified_pairs[name], matches=stats.matches[name]
            )
            image = rec.find_image_with_name(name) if rec is not None else None
            entry["registered"] = bool(image is not None and image.has_pose)
            entry["observations"] = int(image.num_points3D) if entry["registered"] else 0
            if not entry["registered"]:
                entry["why"] = _why_not_registered(name, stats, state.all_models)
        per_image[name] = entry
    return per_image


def build_report(config: Config, state: RunState, status: str, error: str | None) -> dict[str, Any]:
    """poses_report.json: counts, per-image screening / features / matches, why images were left out."""
    rec, stats = state.model, state.stats
    per_image = _per_image(state)
    registered = rec.num_reg_images() if rec is not None else 0
    total = len(stats.features) if stats is not None else len(state.sizes)
    blur = sorted(state.screens[n].blur for n in state.screens)
    checked = verdict(state.checks) if state.checks is not None else {"check": None, "checks": []}
    return {
        "status": status,
        "error": error,
        **checked,
        "choice": state.choice or None,
        "consistency": state.consistency[1],
        "input": str(config.input),
        "registered": registered,
        "total": total,
        "registered_fraction": round(registered / total, 4) if total else 0.0,
        "not_registered": {n: e["why"] for n, e in per_image.items() if "why" in e},
        "left_out": {Path(n).name: why for n, why in state.skipped.items()},
        "models_found": state.models,
        "mean_reprojection_error_px": round(rec.compute_mean_reprojection_error(), 4) if rec is not None else None,
        "points3D": rec.num_points3D() if rec is not None else 0,
        "cameras": {
            str(c): {
                "model": cam.model.name,
                "width": cam.width,
                "height": cam.height,
                "params": [round(float(v), 6) for v in cam.params],
            }
            for c, cam in (rec.cameras.items() if rec is not None else [])
        },
        "principal_point": state.principal_point,
        "radial_term": state.radial_term or "not tried (--no-second-radial-term or one camera per image)",
        "focal_prior": focal_prior_record(state),
        "working_size": state.working_size,
        "attempts": state.attempts,
        "ladder": state.ladder or None,
        "timings_s": {k: round(v, 3) for k, v in state.timings.items()},
        "warnings": state.warnings,
        "screening": {
            "blur_median": round(blur[len(blur) // 2], 2) if blur else None,
            "blur_min": round(blur[0], 2) if blur else None,
            "near_duplicates": state.duplicates,
            "exposure_flags": {n: f for n, sc in state.screens.items() if (f := sc.flags())},
        },
        "video": state.video,
        "masks": state.masks or None,
        "stationary_matches": state.stationary or None,
        "images": per_image,
        "config": config_to_json(config),
    }


def print_summary(console: Console, report: dict[str, Any]) -> None:
    reg, tot = report["registered"], report["total"]
    colour = "green" if tot and reg / tot >= WARN_FRACTION else "yellow"
    err = report["mean_reprojection_error_px"]
    t = sum(report["timings_s"].values())
    tried = attempts_line(report["attempts"])
    console.print(
        f"poses: [{colour}]{reg}/{tot} registered[/{colour}]{tried}, {report['points3D']} points, "
        f"reprojection {err:.2f} px, {t:.1f} s"
        if err is not None
        else f"poses: {reg}/{tot} registered{tried}"
    )
    for w in report["warnings"]:
        console.print(f"[yellow]warning:[/yellow] {w}")
    for c in report["checks"]:
        if not c["ok"]:
            console.print(f"[yellow]warning:[/yellow] {check_line('poses', 'colmap/sparse', c)}")


def focal_prior_record(state: RunState) -> dict[str, Any]:
    """poses_report.json "focal_prior": whether the photos' EXIF gave a focal length, and each camera's prior."""
    values = [p.focal_px for p in state.exif_focal.values()]
    photos = len(state.names)
    weak = sorted({p.weak for p in state.exif_focal.values() if p.weak})
    if weak:
        says = (
            f"weak: {weak[0]}; COLMAP's cameras start from it without has_prior_focal_length, and the "
            "focal_vs_weak_exif check compares the model's with it but never decides which attempt is kept"
        )
    elif values:
        says = (
            "COLMAP's cameras start from the EXIF focal length (has_prior_focal_length) and the focal_vs_exif "
            "check compares the model's with it"
        )
    else:
        says = (
            "absent: no photo's EXIF gives a focal length (FocalLengthIn35mmFilm, or FocalLength with "
            "FocalPlaneXResolution), so COLMAP starts from 1.2 x the long side and calibrates it alone; the "
            "field_of_view check stands in for the EXIF one"
        )
    return {
        "exif": f"{len(values)} of {photos} photos" if values else "absent",
        "strength": ("weak" if weak else "strong") if values else None,
        "focal_px_median": round(float(np.median(values)), 2) if values else None,
        "sources": sorted({p.source for p in state.exif_focal.values()})[:5],
        "says": says,
        "cameras": {str(c): info for c, info in state.focal_prior.items()},
    }


class PhaseTimer:
    """`with timer("features"): ...` times a phase into the state, the progress bar and metrics.csv.

    Set `attempt` (> 1) while retrying: metrics.csv then names the phase "features (attempt 2)"; the report's
    timings_s add up each phase over all attempts.
    """

    def __init__(self, state: RunState, metrics: MetricsLog, progress: Progress | None):
        self.state, self.metrics, self.progress = state, metrics, progress
        self.attempt = 1
        self.task = progress.add_task("poses", total=None) if progress is not None else None

    def __call__(self, phase: str):
        timer = self
        label = phase if self.attempt == 1 else f"{phase} (attempt {self.attempt})"

        class _Phase:
            def __enter__(self):
                if timer.progress is not None:
                    timer.progress.update(timer.task, description=f"poses: {label}")
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                state = timer.state
                state.timings[phase] = state.timings.get(phase, 0.0) + time.perf_counter() - self.t0
                if exc[0] is None:
                    registered = state.model.num_reg_images() if state.model is not None else ""
                    timer.metrics.append(
                        step=len(timer.metrics.rows),
                        seconds=round(time.time() - state.started, 3),
                        phase=label,
                        images=len(state.sizes) or len(state.names),
                        registered=registered,
                    )
                return False

        return _Phase()
