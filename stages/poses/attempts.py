"""The retry ladder of the poses stage: which settings each attempt uses, when it stops, which model it keeps.

Attempt 1 runs the Config as given. Until `choice.stop_reason` says stop (an attempt registered WARN_FRACTION,
80 %, of the images AND its cameras pass `quality`'s checks; or, with a usable model in hand, the retries spent
their time budget), the stage tries, cheapest first:
  2. "more features": pycolmap's defaults: SIFT at 3200 px (or the first attempt's size if larger; never
     above the photos' own size) and a cap of 8192 features (or the first attempt's if larger; doubled when
     that would repeat attempt 1's extraction), plain matching, the default mapper;
  3. "relaxed mapper": attempt 2's features and matches, mapped again with `RELAXED_MAPPER`'s thresholds
     (costs only the mapping);
  4. "guided matching": attempt 2's features, matched again with guided matching (more inliers per pair;
     verification also keeps pairs with as few inliers as the relaxed mapper accepts), relaxed mapper.
Every extraction's cameras get the photos' EXIF focal prior before matching (`exif`). Every attempt's model is
checked (`quality`), and `choice.choose` keeps the one that registered most among those whose cameras pass the
checks and that registered at least FAIL_FRACTION (40 %); only when there is none, the most registered, marked
suspect with a warning. Attempt 2 is pycolmap's own defaults (bar first_octave, see `colmap.SMALL_IMAGE`, and
the seeds) and is never skipped for time, so a set that ends under 80 % should not end with fewer images than
pycolmap's defaults register unless their model failed a camera check (a set at 80 %+ with sane cameras after
attempt 1 is not retried). tests/test_poses.py checks this on a small synthetic set; COLMAP's randomness makes
it no proof.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap

from nerfpipe.data.checks import verdict
from nerfpipe.data.rundir import config_to_json
from nerfpipe.stages.poses import colmap as sfm
from nerfpipe.stages.poses.choice import RETRY_BUDGET, RETRY_MIN_SECONDS, candidate, choose, retry_budget, stop_reason
from nerfpipe.stages.poses.colmap import PYCOLMAP_MAX_IMAGE_SIZE, PYCOLMAP_MAX_NUM_FEATURES, RELAXED_MAPPER, SfmSettings
from nerfpipe.stages.poses.exif import apply_focal_priors
from nerfpipe.stages.poses.report import WARN_FRACTION, PhaseTimer, RunState, textured

__all__ = ["Attempt", "ladder", "describe", "run_attempts", "prior_focals", "LADDER_RULE"]

LADDER_RULE = (
    f"stop at an attempt that registers >= {WARN_FRACTION:.0%} of the images and whose cameras pass the checks; "
    f"once a usable model (cameras passing) exists, start no retry after the retries took max({RETRY_BUDGET:g} x "
    f"the first attempt's time, {RETRY_MIN_SECONDS:g} s) (retry_budget_s)"
)
"""The ladder's stopping rule, as poses_report.json states it (`choice.stop_reason`)."""


@dataclass(frozen=True, kw_only=True)
class Attempt:
    name: str
    settings: SfmSettings
    reuse: Literal["nothing", "features", "matches"] = "nothing"
    """What to take from the last attempt that extracted features: its features (match again) or its
    features and matches (map again)."""


def ladder(first: SfmSettings, max_attempts: int, long_side: int) -> list[Attempt]:
    """The attempts to make, in order, at most `max_attempts` (>= 1) of them, for photos whose long side is
    `long_side` px (a working size above it is the same as the photos' size)."""
    if max_attempts < 1:
        raise ValueError(f"max_attempts must be >= 1, got {max_attempts}")
    size = max(first.max_image_size, PYCOLMAP_MAX_IMAGE_SIZE)
    cap = max(first.max_num_features, PYCOLMAP_MAX_NUM_FEATURES)
    if min(size, long_side) == min(first.max_image_size, long_side) and cap == first.max_num_features:
        cap *= 2  # the same extraction again would find the same features
    more = replace(first, max_image_size=size, max_num_features=cap)
    relaxed = replace(more, mapper=RELAXED_MAPPER)
    guided = replace(relaxed, guided_matching=True, min_verified_inliers=RELAXED_MAPPER.min_num_matches)
    return [
        Attempt(name="as configured", settings=first),
        Attempt(name="more features", settings=more),
        Attempt(name="relaxed mapper", settings=relaxed, reuse="matches"),
        Attempt(name="guided matching", settings=guided, reuse="features"),
    ][:max_attempts]


def describe(settings: SfmSettings, long_side: int) -> str:
    """One line: what an attempt's settings are, for photos whose long side is `long_side` px."""
    t = settings.mapper
    return (
        f"SIFT at {min(settings.max_image_size, long_side)} px, {settings.max_num_features} features, "
        f"{'guided' if settings.guided_matching else 'plain'} {settings.matcher} matching, mapper "
        f"min_num_matches {t.min_num_matches}, init_min_num_inliers {t.init_min_num_inliers}, "
        f"abs_pose_min_num_inliers {t.abs_pose_min_num_inliers}"
    )


def run_attempts(
    plan: list[Attempt],
    build: Path,
    images: Path,
    groups: list[list[str]],
    long_sides: list[int],
    state: RunState,
    phase: PhaseTimer,
    after_matching: Callable[[Path], None] | None = None,
) -> None:
    """Run `plan` until `choice.stop_reason` says stop. Leaves the kept attempt's (`choice.choose`) statistics,
    models and camera priors in `state`, its database at build/database.db, one record per attempt (with its
    checks) in `state.attempts`, and the choice and the ladder's stop in `state.choice` / `state.ladder`.
    Each extraction gets the photos' EXIF focal priors (`exif.apply_focal_priors`, before matching).
    `after_matching(database)` runs once, after the first attempt's matching (it may raise to stop before mapping)."""
    total = sum(len(g) for g in groups)
    results, candidates, seconds = [], [], []  # per attempt: (database, statistics, models, model, priors)
    db = extracted = build / "database.db"
    priors: dict[int, dict] = {}
    stopped = f"every attempt allowed was made (max_attempts {len(plan)})"
    for k, attempt in enumerate(plan, 1):
        phase.attempt, t0, s = k, time.perf_counter(), attempt.settings
        state.model, models = None, {}
        if attempt.reuse != "matches":
            db = build / f"database.{k}.db"
            with phase("features"):
                if attempt.reuse == "features":
                    _copy_features(extracted, db)
                else:
                    sfm.extract(db, images, groups, long_sides, s)
                    priors = apply_focal_priors(db, {n: p.focal_px for n, p in state.exif_focal.items()})
                    extracted = db
                state.stats = sfm.database_stats(db)
            if textured(state.stats):
                with phase("matching"):
                    sfm.match(db, s)
                    state.stats = sfm.database_stats(db)
                if k == 1 and after_matching is not None:
                    after_matching(db)
        if textured(state.stats):
            with phase("mapping"):
                models = sfm.reconstruct(db, images, build / "models" / str(k), s)
                if models:
                    state.model = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()))
        found = candidate(attempt.name, state.model, prior_focals(priors), total)
        seconds.append(time.perf_counter() - t0)
        state.attempts.append(
            {
                "attempt": k,
                "name": attempt.name,
                "registered": found.registered,
                "total": total,
                "models_found": sorted((m.num_reg_images() for m in models.values()), reverse=True),
                "features_median": float(np.median(list(state.stats.features.values()))) if state.stats.features else 0,
                "seconds": round(seconds[-1], 3),
                "reused": attempt.reuse,
                "kept": False,
                "cameras_pass": found.sane,
                **(verdict(found.checks) if state.model is not None else {"check": None, "checks": []}),
                "settings": describe(s, max(long_sides)),
                "options": config_to_json(s),
            }
        )
        results.append((db, state.stats, models, state.model, priors))
        candidates.append(found)
        reason = stop_reason(candidates, total, seconds)
        if reason is not None:
            stopped = reason
            break
    chosen = choose(candidates, total)
    kept_db, state.stats, state.all_models, state.model, state.focal_prior = results[chosen.index]
    state.attempts[chosen.index]["kept"] = True
    state.models = state.attempts[chosen.index]["models_found"]
    state.choice = chosen.sentence
    if chosen.warning is not None:
        state.warnings.append(chosen.warning)
    state.ladder = {"stopped": stopped, "retry_budget_s": round(retry_budget(seconds[0]), 1), "rule": LADDER_RULE}
    phase.attempt = 1
    os.replace(kept_db, build / "database.db")
    for other in build.glob("database.*.db"):
        other.unlink()


def prior_focals(cameras: dict[int, dict]) -> dict[int, float | None]:
    """camera id -> prior focal px (None: absent), from `exif.apply_focal_priors`' record."""
    return {c: info["prior_px"] for c, info in cameras.items()}


def _copy_features(src: Path, dst: Path) -> None:
    """A copy of database `src` with its features only (matches and two-view geometries cleared)."""
    shutil.copyfile(src, dst)
    db = pycolmap.Database.open(dst)
    try:
        db.clear_matches()
        db.clear_two_view_geometries()
    finally:
        db.close()
