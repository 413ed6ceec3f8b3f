"""ONE cause for a training run that went wrong, named from its evidence (`train`'s `cause` check, issue 53).

A run's checks (`stages.train.checks`) say what is wrong: the held-out PSNR is low, the training photos are not
fitted, the views disagree. Users need the why: "poses, background rule or too little training" names three
causes and finds none. `diagnose` weighs the evidence the run has, in this order, and names the first cause it
supports:

1. **poses (the poses stage said so)**: the scene's poses_report.json (beside transforms.json) failed a check of
   the poses against the photos (`capture_order`: the reconstruction folded where faces look alike;
   `look_alike_matches`) or a camera check. The poses stage's own evidence, independent of the field.
2. **background rule**: a background asked for (`--background black|white|random`) contradicts the opaque photos'
   plain border colour and the training photos are not fitted (`background.background_conflict`: `make demo`'s
   white-backed photos with `--background black`, 2.0 dB after 400 steps, were named "poses" before); or the field
   fills most of the space its training cameras see (occupied_share): a fog of density, which is what a background
   rule that keeps the backdrop (or a box that is wrong) trains.
3. **too little training**: the training PSNR still rose by over RISE_DB in the run's last fifth (a run too short
   for that measure: over its last 40 %): the run was cut while learning (more --max-seconds is the cure; the poses
   cannot be judged before the field has fitted its photos).
4. **poses of some views**: over UNEXPLAINED_SHARE of the training views are far under the median view, the rest
   fit: those photos contradict the others (mis-posed, blurred or exposed differently); the worst are named.
5. **poses (contradicting photos)**: the field cannot fit its own training photos (training_fit) and has stopped
   improving: the photos contradict one another, across the board. Wrong poses do that; so would a scene that
   moved, which a user knows.
6. **generalisation**: the training photos are fitted (training PSNR >= TRAIN_FIT_DB) but the held-out ones are
   not (holdout_gap, holdout_psnr): the field learned the photos, not the scene: too few views round the object,
   or held-out photos posed apart from the rest.
7. **empty field** / **pose refinement**: the grid is empty; refinement hit its bounds.
No cure is applied here: the one cheap cure known for wrong poses of this kind (matching restricted to
neighbours in capture order) is the poses stage's, which applies it itself and records that it did.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["Evidence", "diagnose", "RISE_DB", "UNEXPLAINED_SHARE", "TRAIN_FIT_DB", "POSE_CHECKS"]

RISE_DB = 1.0
UNEXPLAINED_SHARE = 0.2
TRAIN_FIT_DB = 20.0
"""A training PSNR under this at the end: the field does not fit its own photos (`checks`' training_fit)."""
POSE_CHECKS = ("capture_order", "look_alike_matches")
"""poses_report.json checks of the poses against the photos (stages.poses.consistency)."""
CAMERA_CHECKS = ("focal_vs_exif", "field_of_view", "focal_aspect", "distortion", "principal_point")
"""poses_report.json checks of the cameras (stages.poses.quality.CAMERA_CHECKS)."""


@dataclass(frozen=True, kw_only=True)
class Evidence:
    """What a finished run knows about itself."""

    failed: dict[str, Any]
    """The failed checks: name -> value."""
    train_psnr: float | None
    """Training PSNR at the end (dB)."""
    test_psnr: float | None
    rise: float | None
    """Training PSNR rise over the run's last fifth (dB; None for a run with under 8 logged rows)."""
    steps: int | None
    per_view: dict[str, Any] | None
    """The manifest's per-view summary (`suspect`, `views_total`, `worst`)."""
    occupied: float | None
    """The occupied share of the cells the training cameras see (`fog.seen_occupied_share`)."""
    poses_report: dict[str, Any] | None
    """The scene's poses_report.json, if the poses stage made the scene."""
    late_rise: float | None = None
    """Training PSNR at the end minus at 60 % of the run's time (dB): the trend of a short run (3+ rows)."""
    background_conflict: str | None = None
    """Where an asked-for background contradicts the photos' plain border colour, the line saying so."""


def _db(value: float | None) -> str:
    return "?" if value is None else f"{value:.2f} dB"


def diagnose(e: Evidence) -> tuple[str, str]:
    """(cause, one line saying it with its evidence) for a run with at least one failed check (module doc)."""
    fit = f"training PSNR {_db(e.train_psnr)} after {e.steps if e.steps is not None else '?'} steps"
    held = f", held-out {_db(e.test_psnr)}" if e.test_psnr is not None else ""
    poses_failed = [
        c
        for c in (e.poses_report or {}).get("checks", [])
        if not c.get("ok", True) and c.get("name") in (*POSE_CHECKS, *CAMERA_CHECKS)
    ]
    if poses_failed:
        c = poses_failed[0]
        return "poses", (
            f"poses: the poses stage's own check {c['name']} = {c['value']} failed ({c.get('says', '')}); the "
            f"field trained on those poses ({fit}{held}): rerun poses (see poses_report.json) before training"
        )
    low_fit = e.train_psnr is not None and e.train_psnr < TRAIN_FIT_DB
    if e.background_conflict is not None and (low_fit or "training_fit" in e.failed):
        return "background rule", (
            f"background rule: {e.background_conflict}: the field cannot fit photos whose backdrop it is told is "
            f"another colour ({fit}{held}); train with --background auto (the photos' own colour)"
        )
    if "occupied_share" in e.failed:
        return "background rule", (
            f"background rule: the field fills {e.occupied:.0%} of the space its training cameras see, a fog "
            f"rather than an object ({fit}{held}): the background was learned as density; try --background white "
            "(or black), or masks"
        )
    climbing = e.rise if e.rise is not None else e.late_rise
    if (
        climbing is not None
        and climbing > RISE_DB
        and (low_fit or {"training_fit", "holdout_psnr", "still_improving"} & set(e.failed))
    ):
        window = "the run's last fifth" if e.rise is not None else "the run's last 40 %"
        return "too little training", (
            f"too little training: the training PSNR still rose {climbing:.1f} dB over {window} ({fit}{held}): "
            "give it more --max-seconds (the poses cannot be judged before the field has fitted its photos)"
        )
    views = e.per_view or {}
    total = views.get("views_total") or 0
    suspect = views.get("suspect") or []
    if total and len(suspect) / total > UNEXPLAINED_SHARE:
        named = ", ".join(str(v).rsplit("/", 1)[-1] for v in suspect[:4])
        return "poses of some views", (
            f"poses of some views: {len(suspect)} of {total} training views are far under the median view "
            f"({named}{', ...' if len(suspect) > 4 else ''}), the rest fit ({fit}{held}): those photos contradict "
            "the others (mis-posed, blurred or exposed differently; per_view_worst.png shows them)"
        )
    if "training_fit" in e.failed or (low_fit and "holdout_psnr" in e.failed):
        rose = f", {climbing:+.1f} dB over the run's end" if climbing is not None else ""
        return "poses", (
            f"poses: the field cannot fit its own training photos ({fit}{rose}: it stopped improving) and no view "
            "stands out: the photos contradict one another across the board, which wrong poses do (or a scene "
            "that moved); check the poses against the photos (poses_report.json) or rerun poses"
        )
    if ("holdout_gap" in e.failed or "holdout_psnr" in e.failed) and not low_fit:
        return "generalisation", (
            f"generalisation: the field fits its training photos ({fit}) but not the held-out ones"
            f"{held.replace(', held-out', ':')}: it learned the photos, not the scene (too few views round the "
            "object, or held-out photos posed apart from the rest)"
        )
    if "still_improving" in e.failed:
        return "too little training", f"too little training: the training PSNR still rose ({fit}): more --max-seconds"
    if "occupied_share_min" in e.failed:
        return "empty field", f"empty field: the occupancy grid is empty ({fit}): the scene's box or near/far is wrong"
    if "pose_corrections" in e.failed:
        return "pose refinement", f"pose refinement: corrections hit their bounds ({fit}{held}): run without it"
    if "unexplained_views" in e.failed:
        return "poses of some views", f"poses of some views: {len(suspect)} of {total} views far under the median"
    name = next(iter(e.failed))
    return name, f"{name}: see that check ({fit}{held})"
