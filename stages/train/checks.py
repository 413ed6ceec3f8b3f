"""The train stage's self-check of its run (`data.checks`): the manifest's `check` and `checks`.

Each rule, its limit and why (figures from `make bench-real`, docs/BENCH_REAL.md, and the cases of issue 27):
- **holdout_psnr** >= data.checks.HOLDOUT_FLOOR_DB on the full test images (eval applies the same floor).
- **holdout_gap**: the training PSNR at the end (the last LAST_ROWS logged rows) minus the held-out PSNR,
  <= data.checks.HOLDOUT_GAP_DB: a field that reproduces its photos but not the held-out ones has learned the
  photos, not the scene (mis-posed or too few views, a background rule that erased the object).
- **still_improving**: the training PSNR's rise over the last RISE_WINDOW of the run's time, <= RISE_DB: a run
  still climbing steeply when the budget ran out is undertrained (more --max-seconds would change the result).
- **unexplained_views**: training views more than report.SUSPECT_DB under the median view (per_view.json), at most
  UNEXPLAINED_SHARE of them: many is a capture the field could not explain (blur, exposure, poses).
- **occupied_share** (fast field, box scenes): the share of the occupancy cells the training cameras see where
  the field's density at the end is over the grid's threshold (`fog.seen_occupied_share`), <= FOG_SHARE: an
  object fills a fraction of the space its cameras see, a fog of density fills it all. (The grid's own marks are
  conservative and stale by design: they made `make demo`'s sound field a 64 % "fog"; the field's own share of
  the cells its cameras see is 16 % there.)
- **occupied_share_min** (fast field): the share of all occupancy cells occupied > 0 (an empty field renders
  nothing).
- **pose corrections** (--refine-poses): the guard's record (`model.camera_opt.pose_report`): refinement pulled
  back or stopped is reported with its figures.
- **training_fit**: the training PSNR at the end >= TRAIN_FIT_DB: under it the field cannot reproduce even the
  photos it trains on (issue 53: a folded carton 16.97 dB after 395 steps; the same kind of capture with right
  poses, the shared head on white, 24.95 dB after 575). Left out of runs that logged under LAST_ROWS rows.
- **cause** (only when another check failed): ONE cause named from the evidence (`diagnose`), in one line, instead
  of a list of possibilities. See `diagnose` for the rules and their order.
Checks that do not apply (no test split, no refinement, no training PSNR logged: a run shorter than one logging
interval) are left out.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from nerfpipe.data.checks import HOLDOUT_FLOOR_DB, HOLDOUT_GAP_DB, Check
from nerfpipe.stages.train.diagnosis import RISE_DB, TRAIN_FIT_DB, UNEXPLAINED_SHARE, Evidence, diagnose

__all__ = ["train_checks", "HOLDOUT_FLOOR_DB", "GAP_DB", "RISE_DB", "TRAIN_FIT_DB"]

GAP_DB = HOLDOUT_GAP_DB
LAST_ROWS = 4
RISE_WINDOW = 0.2
FOG_SHARE = 0.6


def _series(rows: list[dict], key: str) -> list[tuple[float, float]]:
    return [(float(r["seconds"]), float(r[key])) for r in rows if r.get(key) not in (None, "")]


def _train_psnr_end(rows: list[dict]) -> float | None:
    """Mean training PSNR of the last LAST_ROWS logged rows; None when the run logged none (shorter than one logging
    interval)."""
    pts = _series(rows, "train_psnr")
    return float(np.mean([p for _, p in pts[-LAST_ROWS:]])) if pts else None


def _rise(rows: list[dict]) -> float | None:
    """Mean training PSNR over the last RISE_WINDOW of the run's time minus over the window before it."""
    pts = _series(rows, "train_psnr")
    if len(pts) < 8:
        return None
    end = pts[-1][0]
    last = [p for s, p in pts if s > end * (1 - RISE_WINDOW)]
    before = [p for s, p in pts if end * (1 - 2 * RISE_WINDOW) < s <= end * (1 - RISE_WINDOW)]
    if not last or not before:
        return None
    return float(np.mean(last) - np.mean(before))


def train_checks(
    *,
    rows: list[dict],
    test_psnr: float | None,
    per_view: dict[str, Any] | None,
    occupied: float | None,
    object_box: bool,
    pose: dict[str, Any] | None,
    scene_dir: Path | None = None,
    seen_occupied: float | None = None,
    background_conflict: str | None = None,
) -> list[Check]:
    """The run's checks from its metrics rows, final held-out PSNR, per-view report, occupied cell share (None
    without a grid) and that share among the cells the training cameras see (None: not measured, the share of
    all cells stands in), the asked-for background's contradiction of the photos (`background.background_conflict`;
    evidence for `diagnose`), whether the field's box is the object's own (`radiance.space.Space.object_box`), the
    pose-refinement record (None without refinement) and the scene folder (where the poses stage's
    poses_report.json may lie beside transforms.json: evidence for `diagnose`)."""
    out: list[Check] = []
    if test_psnr is not None:
        out.append(
            Check.lower(
                "holdout_psnr",
                test_psnr,
                HOLDOUT_FLOOR_DB,
                unit=" dB",
                says="the field reproduces the held-out photos poorly (the cause check names why)",
            )
        )
    train_end = _train_psnr_end(rows)
    if test_psnr is not None and train_end is not None:
        out.append(
            Check.upper(
                "holdout_gap",
                train_end - test_psnr,
                GAP_DB,
                unit=" dB",
                says="training photos are reproduced far better than held-out ones: the field learned "
                "the photos, not the scene (mis-posed or too few views)",
            )
        )
    rise = _rise(rows)
    if rise is not None:
        out.append(
            Check.upper(
                "still_improving",
                rise,
                RISE_DB,
                unit=" dB",
                says=f"training PSNR still rose this much over the last {RISE_WINDOW:.0%} of the run: "
                "undertrained, more --max-seconds would change the result",
            )
        )
    if per_view and per_view.get("views_total"):
        share = len(per_view.get("suspect", [])) / per_view["views_total"]
        out.append(
            Check.upper(
                "unexplained_views",
                share,
                UNEXPLAINED_SHARE,
                says="many training views are far under the median view's PSNR (per_view_worst.png): "
                "blur, exposure or poses the field cannot explain",
            )
        )
    fog = seen_occupied if seen_occupied is not None else occupied
    if occupied is not None:
        out.append(
            Check.lower(
                "occupied_share_min", occupied, 1e-4, says="the occupancy grid is empty: the field renders nothing"
            )
        )
        if object_box:
            out.append(
                Check.upper(
                    "occupied_share",
                    fog,
                    FOG_SHARE,
                    says="most of the space the training cameras see is occupied: a fog of density rather than "
                    "an object (the background rule or the box may be wrong)",
                )
            )
    if pose is not None and "guard" in pose:
        guard = pose["guard"]
        out.append(
            Check(
                name="pose_corrections",
                ok=not guard.get("suspect"),
                value=guard.get("summary", ""),
                limit=guard.get("limit", ""),
                says="pose refinement hit its bounds: corrections beyond what a capture's poses can be "
                "off by were pulled back or refinement was stopped",
            )
        )
    if train_end is not None and len(_series(rows, "train_psnr")) >= LAST_ROWS:
        out.append(
            Check.lower(
                "training_fit",
                train_end,
                TRAIN_FIT_DB,
                unit=" dB",
                says="the field cannot reproduce even its own training photos (the cause check names why)",
            )
        )
    if any(not c.ok for c in out):
        evidence = Evidence(
            failed={c.name: c.value for c in out if not c.ok},
            train_psnr=train_end,
            test_psnr=test_psnr,
            rise=rise,
            late_rise=_late_rise(rows),
            steps=_last_step(rows),
            per_view=per_view,
            occupied=fog,
            background_conflict=background_conflict,
            poses_report=_poses_report(scene_dir),
        )
        cause, line = diagnose(evidence)
        out.append(Check(name="cause", ok=False, value=cause, limit="none (every other check passes)", says=line))
    return out


def _late_rise(rows: list[dict]) -> float | None:
    """Training PSNR at the last logged row minus at the last row logged before 60 % of the run's time: the trend
    of a run too short for `_rise` (3+ logged rows); None with fewer."""
    pts = _series(rows, "train_psnr")
    if len(pts) < 3:
        return None
    before = [p for s, p in pts if s <= 0.6 * pts[-1][0]]
    return pts[-1][1] - before[-1] if before else None


def _last_step(rows: list[dict]) -> int | None:
    steps = [int(float(r["step"])) for r in rows if r.get("step") not in (None, "")]
    return steps[-1] if steps else None


def _poses_report(scene_dir: Path | None) -> dict[str, Any] | None:
    """The poses stage's poses_report.json beside the scene's transforms.json, or None (a posed dataset has none;
    an unreadable one is no evidence)."""
    if scene_dir is None:
        return None
    path = Path(scene_dir) / "poses_report.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None
