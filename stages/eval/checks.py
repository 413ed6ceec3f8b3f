"""eval's self-check: held-out PSNR against its floor, and the gap to the run's training PSNR."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from nerfpipe.data.checks import HOLDOUT_FLOOR_DB, HOLDOUT_GAP_DB, Check

__all__ = ["MIN_PSNR", "MAX_GAP_DB", "train_psnr", "self_checks"]


MIN_PSNR = HOLDOUT_FLOOR_DB
"""Self-check: the held-out PSNR (dB) under which the renders are suspect in themselves (`data.checks`)."""


MAX_GAP_DB = HOLDOUT_GAP_DB
"""Self-check: how far (dB) the held-out PSNR may fall under the run's train PSNR (`data.checks`)."""


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
