"""The retry ladder of the poses stage: which settings each attempt uses, when it stops, which model it keeps.

Attempt 1 runs the Config as given. Until `choice.stop_reason` says stop (an attempt registered WARN_FRACTION,
80 %, of the images AND its cameras pass `quality`'s checks AND its poses agree with the photos; or, with such a
usable model in hand, the retries spent their time budget), the stage tries, cheapest first:
  2. "more features": pycolmap's defaults: SIFT at 3200 px (or the first attempt's size if larger; never
     above the photos' own size) and a cap of 8192 features (or the first attempt's if larger; doubled when
     that would repeat attempt 1's extraction), plain matching, the default mapper;
  3. "relaxed mapper": attempt 2's features and matches, mapped again with `RELAXED_MAPPER`'s thresholds
     (costs only the mapping);
  4. "wide-baseline features": new features made to survive larger changes of viewpoint
     (`colmap.SfmSettings.wide_baseline`: SIFT upsampled 2x, DSP-SIFT, affine shapes) at attempt 1's working size
     or 1000 px if smaller, attempt 1's cap, guided matching with pycolmap's verification (15 inliers a pair),
     relaxed mapper. For photos taken far apart (22 photos all round a masked head, ~16 deg apart, 1000 px: 11-13
     registered by the other attempts, 20 by this one, all within 1 deg; docs/BENCH_POSES.md);
  5. "guided matching": the last plain extraction's features (attempt 2's), matched again with guided matching
     (more inliers per pair; verification also keeps pairs with as few inliers as the relaxed mapper accepts),
     relaxed mapper. After attempt 4, not before: its weak pairs misplaced cameras on that sparse set (15/22
     registered, 2.0 deg median rotation error, against 0.4 deg), and its mapping is the ladder's slowest.
Every extraction's cameras get the photos' EXIF focal prior before matching (`exif`). Every attempt's model is
checked (`quality`) and compared with the photos' matches (`consistency`); `choice.choose` keeps the one that
registered most among those whose cameras pass the checks, whose poses agree with the photos and that registered
at least FAIL_FRACTION (40 %); only when there is none, the most registered, marked suspect with a warning.
Where attempt 1 found ENOUGH_FEATURES (1,000) or more SIFT features a photo (median) and did not fold, attempt 4
moves up to be the first retry (`_wide_first`; the report's `ladder.reordered`): the photos lack links, not features.
An attempt whose model folded along the capture order (`consistency.creases`: consecutive photos that share
matches placed far apart, or whose matches it contradicts) is followed at once by
  "neighbours in capture order": its features and matches, the verified pairs restricted to photos within
     `consistency.neighbour_window` places of one another in name order (a face is then matched only with the
     photos taken next to it, never with a look-alike face on the other side), mapped again (costs a mapping,
     usually cheaper than the first: fewer, consistent pairs);
  "far-matched features dropped": the last extraction's matches without those of features that also match a photo
     over the window away in capture order (`far_matched`: a turntable's room that did not turn, or faces that look
     alike), verified again and mapped with the relaxed thresholds (the shared head as shot, no masks: every other
     attempt folded, 8.4 deg median error; this one 66/66 at 1.07 deg, docs/BENCH_POSES.md);
the second only when the first folded too; each takes the place of the ladder's last attempt (max_attempts still
bounds the count). Each attempt's record says how far its rotations between two cameras differ from the kept
model's (`consistency.rotation_disagreement`).
"more features" is pycolmap's own defaults (bar first_octave, see `colmap.SMALL_IMAGE`, and the seeds) and runs
whatever the budget while no usable model exists, so a set that ends unusable should not end with fewer images
than pycolmap's defaults register unless their model failed a check (a set at 80 %+ with sane cameras after
attempt 1 is not retried; with a usable model in hand the budget may leave it out). tests/test_poses.py checks this
on a small synthetic set; COLMAP's randomness makes it no proof.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from nerfpipe.data.checks import verdict
from nerfpipe.data.rundir import config_to_json
from nerfpipe.stages.poses import colmap as sfm
from nerfpipe.stages.poses.budget import AttemptCost, attempt_cost, fit_retry
from nerfpipe.stages.poses.choice import Candidate, agreement, candidate, choose, keepable, stop_reason
from nerfpipe.stages.poses.colmap import (
    ENOUGH_FEATURES,
    PYCOLMAP_MAX_IMAGE_SIZE,
    PYCOLMAP_MAX_NUM_FEATURES,
    PYCOLMAP_MIN_VERIFIED_INLIERS,
    RELAXED_MAPPER,
    WORKING_SIZES,
    SfmSettings,
)
from nerfpipe.stages.poses.consistency import (
    consistency_checks,
    restrict_to_neighbours,
)
from nerfpipe.stages.poses.exif import apply_focal_priors
from nerfpipe.stages.poses.far_matched import drop_far_matched
from nerfpipe.stages.poses.images import natural_key
from nerfpipe.stages.poses.report import WARN_FRACTION, PhaseTimer, RunState, textured

__all__ = ["Attempt", "ladder", "describe", "run_attempts", "prior_focals", "weak_priors", "LADDER_RULE"]

LADDER_RULE = (
    f"stop at an attempt that registers >= {WARN_FRACTION:.0%} of the images, whose cameras pass the checks and "
    "whose poses agree with the photos; a model that folded along the capture order is retried at once with the "
    "matches restricted to neighbours in capture order; once a usable model (cameras passing, poses consistent) "
    "exists, start no retry past the stage's time budget (time_budget_s), nor one predicted to end past it (an "
    "extraction retry is first shrunk to fit)"
)
"""The ladder's stopping rule, as poses_report.json states it (`choice.stop_reason`)."""


@dataclass(frozen=True, kw_only=True)
class Attempt:
    name: str
    settings: SfmSettings
    reuse: Literal["nothing", "features", "matches", "neighbours", "far_matched"] = "nothing"
    """What to take from the last attempt that extracted features: its features (match again; the last extraction that
    was not wide-baseline) or its features and matches (map again); "neighbours": the database of the attempt just
    made, its verified pairs restricted to neighbours in capture order (map again); "far_matched": the last
    extraction's matched database without the matches of features matched far across the capture order
    (`far_matched.drop_far_matched`), verified again (map again)."""


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
    wide = replace(
        first,
        max_image_size=min(first.max_image_size, WORKING_SIZES[0]),
        mapper=RELAXED_MAPPER,
        guided_matching=True,
        min_verified_inliers=PYCOLMAP_MIN_VERIFIED_INLIERS,
        wide_baseline=True,
    )
    return [
        Attempt(name="as configured", settings=first),
        Attempt(name="more features", settings=more),
        Attempt(name="relaxed mapper", settings=relaxed, reuse="matches"),
        Attempt(name="wide-baseline features", settings=wide),
        Attempt(name="guided matching", settings=guided, reuse="features"),
    ][:max_attempts]


def describe(settings: SfmSettings, long_side: int) -> str:
    """One line: what an attempt's settings are, for photos whose long side is `long_side` px."""
    t = settings.mapper
    return (
        f"{'wide-baseline SIFT (2x upsampled, DSP, affine)' if settings.wide_baseline else 'SIFT'} at "
        f"{min(settings.max_image_size, long_side)} px, {settings.max_num_features} features, "
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
    budget: float = math.inf,
) -> None:
    """Run `plan` until `choice.stop_reason` says stop. Leaves the kept attempt's (`choice.choose`) statistics,
    models and camera priors in `state`, its database at build/database.db, one record per attempt (with its
    checks) in `state.attempts`, the kept model's consistency checks and their record in `state.consistency`, and
    the choice and the ladder's stop in `state.choice` / `state.ladder`.
    Each extraction gets the photos' EXIF focal priors (`exif.apply_focal_priors`, before matching).
    `after_matching(database)` runs once, after the first attempt's matching (it may raise to stop before mapping).
    `budget`: the stage's time budget in seconds from `state.started` (`budget` module: it bounds the retries)."""
    plan = list(plan)
    total = sum(len(g) for g in groups)
    order = sorted((n for g in groups for n in g), key=natural_key)
    results, candidates, records, skipped = [], [], [], []  # per attempt: (database, statistics, models, model, priors)
    db = extracted = build / "database.db"
    source: SfmSettings = plan[0].settings  # the settings of the last extraction
    priors: dict[int, dict] = {}
    evidence_db = db  # the database with every pair the photos gave, that the consistency checks read
    first: AttemptCost | None = None
    stopped = f"every attempt allowed was made (max_attempts {len(plan)})"
    reordered = None
    k = 0
    while k < len(plan):
        attempt = plan[k]
        k += 1
        if attempt.reuse != "nothing":  # its features come from the last extraction: say so in its settings
            attempt = replace(attempt, settings=_extracted_with(attempt.settings, source))
        fitted = _within_budget(attempt, first, candidates, total, state, budget, max(long_sides))
        if fitted is None:
            skipped.append(attempt.name)
            continue
        attempt, budget_note = fitted
        phase.attempt, t0, s, before = k, time.perf_counter(), attempt.settings, dict(state.timings)
        state.model, models, restricted, dropped_far = None, {}, None, None
        own_evidence = None  # the far-matched attempt's model is checked against the matches it kept
        if attempt.reuse == "far_matched":
            db = own_evidence = build / f"database.{k}.db"
            with phase("matching"):
                dropped_far = drop_far_matched(
                    evidence_db, db, order, sfm.verification_options(s), num_threads=s.num_threads
                )
                state.stats = sfm.database_stats(db)
        elif attempt.reuse == "neighbours":
            previous, db = db, build / f"database.{k}.db"
            with phase("matching"):
                kept, dropped, window = restrict_to_neighbours(previous, db, order)
                state.stats = sfm.database_stats(db)
            restricted = {"window": window, "pairs_kept": kept, "pairs_dropped": dropped}
        elif attempt.reuse != "matches":
            db = evidence_db = build / f"database.{k}.db"
            with phase("features"):
                if attempt.reuse == "features":
                    sfm.copy_features(extracted, db)
                else:
                    sfm.extract(db, images, groups, long_sides, s, build / "working")
                    priors = apply_focal_priors(
                        db,
                        {n: p.focal_px for n, p in state.exif_focal.items()},
                        {n: p.weak for n, p in state.exif_focal.items() if p.weak},
                    )
                    if not s.wide_baseline:  # "features" retries re-match plain SIFT (the ladder's doc)
                        extracted, source = db, s
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
        consistency, record = [], None
        if state.model is not None:
            with phase("consistency"):
                consistency, record = consistency_checks(state.model, own_evidence or evidence_db, order)
        found = candidate(
            attempt.name, state.model, prior_focals(priors), total, weak_priors(priors), consistency=consistency
        )
        seconds = time.perf_counter() - t0
        if first is None:
            spent = {p: state.timings.get(p, 0.0) - before.get(p, 0.0) for p in state.timings}
            first = attempt_cost(s, max(long_sides), list(state.stats.features.values()), spent)
        state.attempts.append(
            {
                "attempt": k,
                "name": attempt.name,
                "registered": found.registered,
                "total": total,
                "models_found": sorted((m.num_reg_images() for m in models.values()), reverse=True),
                "features_median": float(np.median(list(state.stats.features.values()))) if state.stats.features else 0,
                "seconds": round(seconds, 3),
                "reused": attempt.reuse,
                "kept": False,
                "cameras_pass": found.sane,
                "poses_consistent": found.consistent if state.model is not None else None,
                **(
                    verdict([*found.checks, *consistency]) if state.model is not None else {"check": None, "checks": []}
                ),
                "consistency": record,
                **({"restricted_to_neighbours": restricted} if restricted else {}),
                **({"far_matched_dropped": dropped_far} if dropped_far else {}),
                **({"budget": budget_note} if budget_note else {}),
                "settings": describe(s, max(long_sides))
                + (f", pairs within {restricted['window']} places in capture order" if restricted else "")
                + (
                    f", without the features matched over {dropped_far['window']} places away in capture order"
                    if dropped_far
                    else ""
                ),
                "options": config_to_json(s),
            }
        )
        results.append((db, state.stats, models, state.model, priors))
        records.append(record)
        candidates.append(found)
        reason = stop_reason(candidates, total, time.time() - state.started, budget)
        if reason is not None:
            stopped = reason
            break
        cure = _fold_cure(plan, attempt) if _folded(found) and k < len(plan) else None
        if cure is not None:
            plan = [*plan[:k], cure, *plan[k:-1]]
        elif k == 1 and first.features >= ENOUGH_FEATURES:
            plan, reordered = _wide_first(plan, first.features)
    chosen = choose(candidates, total)
    kept_db, state.stats, state.all_models, state.model, state.focal_prior = results[chosen.index]
    state.attempts[chosen.index]["kept"] = True
    state.models = state.attempts[chosen.index]["models_found"]
    state.consistency = (list(candidates[chosen.index].consistency), records[chosen.index])
    state.choice = chosen.sentence + agreement(state.attempts, [r[3] for r in results], chosen.index)
    if chosen.warning is not None:
        state.warnings.append(chosen.warning)
    dropped = state.attempts[chosen.index].get("far_matched_dropped")
    if dropped:
        state.warnings.append(
            f"the poses kept were found without the {dropped['keypoints_dropped_share']:.0%} of features that also "
            "match photos far away in capture order: what did not turn with the object (a turntable's room) or "
            "faces that look alike; a room that stood still while the object turned is not one scene with it, and "
            "a field fits it worse than the object: if so, rerun poses with --masks DIR (the object white)"
        )
    if skipped and stopped.startswith("every attempt"):
        stopped = f"the retries that fit the time budget were made ({', '.join(skipped)} did not fit)"
    state.ladder = {
        "stopped": stopped,
        "time_budget_s": None if math.isinf(budget) else round(budget, 1),
        "left_out_for_time": skipped,
        "rule": LADDER_RULE,
        **({"reordered": reordered} if reordered else {}),
    }
    phase.attempt = 1
    os.replace(kept_db, build / "database.db")
    for other in build.glob("database.*.db"):
        other.unlink()


def _extracted_with(settings: SfmSettings, source: SfmSettings) -> SfmSettings:
    """`settings` with the extraction of `source` (an attempt that reuses features was not extracted with its own)."""
    return replace(settings, max_image_size=source.max_image_size, max_num_features=source.max_num_features)


def _within_budget(
    attempt: Attempt,
    first: AttemptCost | None,
    candidates: list[Candidate],
    total: int,
    state: RunState,
    budget: float,
    long_side: int,
) -> tuple[Attempt, str | None] | None:
    """`attempt` as it may run within the time budget (an extraction retry possibly shrunk), with a note for its
    record, or None when it does not fit (`budget` module). Unbounded: the first attempt, the fold cures
    (`_fold_cure`), and every attempt while no usable model the stage would keep exists."""
    if (
        first is None
        or attempt.reuse in ("neighbours", "far_matched")
        or math.isinf(budget)
        or keepable(candidates, total) is None
    ):
        return attempt, None
    left = budget - (time.time() - state.started)
    fitted, _, why = fit_retry(attempt.settings, attempt.reuse, first, left, long_side)
    if fitted is None:
        state.warnings.append(f"retry '{attempt.name}' {why} (poses --time-budget)")
        return None
    return replace(attempt, settings=fitted), why


def _wide_first(plan: list[Attempt], features: float) -> tuple[list[Attempt], str | None]:
    """`plan` with its wide-baseline retry moved right after attempt 1, and why (None: no such retry, or already
    next). Attempt 1's photos had `features` (median) >= ENOUGH_FEATURES: what kept images out was how their
    features link across views, not their number, so new features that survive a change of viewpoint come before
    more of the same (which cost the time budget first: 22 photos all round a masked head at 4000 px, budget
    110 s: "more features" registered 15 of 22 in 71 s and left the wide-baseline retry no time)."""
    wide = [i for i, a in enumerate(plan) if a.settings.wide_baseline]
    if not wide or wide[0] <= 1:
        return plan, None
    i = wide[0]
    moved = [plan[0], plan[i], *plan[1:i], *plan[i + 1 :]]
    return moved, (
        f"'{plan[i].name}' moved before '{plan[1].name}': attempt 1 found {features:.0f} SIFT features a photo "
        f"(median, >= {ENOUGH_FEATURES}), so its unregistered photos lacked links between views, not features"
    )


def _fold_cure(plan: list[Attempt], done: Attempt) -> Attempt | None:
    """The retry to make at once after `done`, an attempt whose model folded, or None: first its matches restricted
    to neighbours in capture order (faces that look alike: a carton's prints); when that folded too, the last
    extraction's matches without the features matched far across the order (what did not turn with the object: a
    turntable's room), mapped with the relaxed thresholds since fewer matches remain. Each once a run."""
    if not any(a.reuse == "neighbours" for a in plan):
        return Attempt(name="neighbours in capture order", settings=done.settings, reuse="neighbours")
    if done.reuse == "neighbours" and not any(a.reuse == "far_matched" for a in plan):
        settings = replace(done.settings, mapper=RELAXED_MAPPER)
        return Attempt(name="far-matched features dropped", settings=settings, reuse="far_matched")
    return None


def _folded(found: Candidate) -> bool:
    """The attempt's model folded along the capture order (its capture_order check failed)."""
    return any(c.name == "capture_order" and not c.ok for c in found.consistency)


def prior_focals(cameras: dict[int, dict]) -> dict[int, float | None]:
    """camera id -> prior focal px (None: absent), from `exif.apply_focal_priors`' record."""
    return {c: info["prior_px"] for c, info in cameras.items()}


def weak_priors(cameras: dict[int, dict]) -> dict[int, str | None]:
    """camera id -> why its prior is only a guess (None: it is not), from `exif.apply_focal_priors`' record."""
    return {c: info.get("weak") for c, info in cameras.items()}
