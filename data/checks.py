"""A stage's self-check of its own result: named checks, each a figure against a limit, and one verdict.

Every stage's manifest (and `poses_report.json`) carries

    "check": "ok" | "suspect",
    "checks": [{"name": str, "ok": bool, "value": number | str, "limit": str, "says": str}, ...]

`check` is "suspect" when any check failed; the failed ones are the reasons, each with its figure (`value`), the
rule it broke (`limit`, e.g. "<= 3 dB") and one sentence (`says`) a user can act on. A check that does not apply to
a result is left out of the list (a box run has no pose corrections to bound), never recorded as passed.

`pipelines/suspects.py` prints the suspect ones of a whole `make` chain, one line each.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

__all__ = ["Check", "verdict", "check_line", "read_failed", "HOLDOUT_FLOOR_DB", "HOLDOUT_GAP_DB"]

HOLDOUT_FLOOR_DB = 18.0
"""train's and eval's floor on the held-out PSNR (dB): between the real-capture table's runs and the wrong runs users
reported (docs/MEASUREMENTS.md, "Self-checks")."""
HOLDOUT_GAP_DB = 6.0
"""train's and eval's bound on the training PSNR minus the held-out PSNR (dB), above the real-capture table's gaps
(docs/MEASUREMENTS.md, "Self-checks")."""


@dataclass(frozen=True, kw_only=True)
class Check:
    name: str
    """Short identifier, e.g. "holdout_gap"."""
    ok: bool
    value: float | int | str
    """The measured figure (rounded for reading)."""
    limit: str
    """The rule, as text: "<= 6 dB", "within 25 % of the EXIF focal"."""
    says: str
    """One sentence: what the figure means for the result (read when the check fails)."""

    @classmethod
    def upper(cls, name: str, value: float, limit: float, says: str, unit: str = "") -> Check:
        """Passes while `value` <= `limit` (a NaN value fails: a figure that cannot be computed is suspect)."""
        ok = bool(not math.isnan(value) and value <= limit)
        return cls(name=name, ok=ok, value=_round(value), limit=f"<= {limit:g}{unit}", says=says)

    @classmethod
    def lower(cls, name: str, value: float, limit: float, says: str, unit: str = "") -> Check:
        """Passes while `value` >= `limit` (a NaN value fails)."""
        ok = bool(not math.isnan(value) and value >= limit)
        return cls(name=name, ok=ok, value=_round(value), limit=f">= {limit:g}{unit}", says=says)


def _round(value: float) -> float | str:
    if math.isnan(value) or math.isinf(value):
        return str(value)
    return float(f"{value:.4g}")


def verdict(checks: Iterable[Check]) -> dict[str, Any]:
    """{"check": "ok" | "suspect", "checks": [...]} for a manifest (merge it into the document's extra fields)."""
    checks = list(checks)
    return {"check": "ok" if all(c.ok for c in checks) else "suspect", "checks": [asdict(c) for c in checks]}


def check_line(stage: str, where: str, check: dict[str, Any]) -> str:
    """One line for a failed check record (as stored in a manifest): who, what, figure, rule, meaning."""
    return f"{stage} ({where}): {check['name']} = {check['value']} (expected {check['limit']}): {check['says']}"


def read_failed(stage: str, path: Path, where: str | None = None) -> tuple[list[str], int]:
    """(one `check_line` per failed check, naming the record as `where` (default: its path), number of checks) of
    the record at `path`; OSError / ValueError / KeyError / TypeError / AttributeError when it cannot be read as a
    record with checks. Used by the CLI after each stage and by `pipelines/suspects.py` after a chain."""
    checks = json.loads(Path(path).read_text()).get("checks") or []
    return [check_line(stage, where or str(path), c) for c in checks if not c["ok"]], len(checks)
