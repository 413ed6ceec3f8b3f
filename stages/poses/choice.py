"""Which attempt of the poses stage's retry ladder to keep, and when the ladder stops.

Keep (`choose`): among the attempts whose model is USABLE (registered >= FAIL_FRACTION of the images, 40 %, and
MIN_REGISTERED), whose cameras pass `quality.CAMERA_CHECKS` and whose poses agree with the photos
(`consistency.consistency_checks`: no fold along the capture order), the one that registered most (then most 3D
points, then the earliest). A model that fails a camera check is kept only when no attempt passes them: then the
one that registered most; one that folded only when no attempt with sane cameras is consistent; each time with a
warning naming the failed checks and their figures (the stage's verdict is "suspect"). The `choice` sentence of
poses_report.json says why the kept one won, what was passed over, and which check decided.

Stop (`stop_reason`, asked after each attempt):
  - an attempt registered >= WARN_FRACTION (80 %), its cameras pass the checks and its poses are consistent: good
    enough, stop. A model at 80 %+ whose camera fails a check, or that folded, does NOT stop the ladder;
  - time (`budget`): once a usable model that the stage would keep (enough registered, cameras passing, poses
    consistent) is in hand, no retry starts after the stage spent its time budget, nor one predicted to end past it
    (`budget.fit_retry`, which may shrink an extraction retry to fit). With no such model every attempt is made:
    the alternative is a failed or a suspect result.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import pycolmap

from nerfpipe.data.checks import Check
from nerfpipe.stages.poses import quality
from nerfpipe.stages.poses.consistency import AGREE_DEG, rotation_disagreement
from nerfpipe.stages.poses.report import FAIL_FRACTION, MIN_REGISTERED, WARN_FRACTION

__all__ = [
    "Candidate",
    "Choice",
    "candidate",
    "choose",
    "stop_reason",
    "usable",
    "keepable",
    "agreement",
]


@dataclass(frozen=True, kw_only=True)
class Candidate:
    """One attempt's kept model, as the choice sees it."""

    name: str
    registered: int
    points: int
    checks: tuple[Check, ...]
    """`quality.model_checks` of the model (empty when the attempt made none)."""
    consistency: tuple[Check, ...] = ()
    """`consistency.consistency_checks` of the model: its poses against the photos' matches."""

    @property
    def sane(self) -> bool:
        """It has a model whose cameras pass every camera check."""
        return self.registered > 0 and quality.cameras_pass(list(self.checks))

    @property
    def consistent(self) -> bool:
        """Its poses pass every consistency check (no fold along the capture order)."""
        return all(c.ok for c in self.consistency)


@dataclass(frozen=True, kw_only=True)
class Choice:
    index: int
    """Position of the kept attempt in the candidates."""
    sentence: str
    """Why it won (poses_report.json "choice")."""
    warning: str | None
    """Set when the kept model fails a camera check."""


def candidate(
    name: str,
    rec: pycolmap.Reconstruction | None,
    priors: dict[int, float | None],
    total: int,
    weak: dict[int, str | None] | None = None,
    consistency: Sequence[Check] = (),
) -> Candidate:
    """The Candidate of an attempt's model `rec` (None: it made none); `priors`: camera id -> EXIF focal px,
    `weak`: camera id -> why that prior is a guess; `consistency`: the model's consistency checks."""
    if rec is None:
        return Candidate(name=name, registered=0, points=0, checks=())
    checks = tuple(quality.model_checks(rec, priors, total, weak))
    return Candidate(
        name=name,
        registered=rec.num_reg_images(),
        points=rec.num_points3D(),
        checks=checks,
        consistency=tuple(consistency),
    )


def usable(registered: int, total: int) -> bool:
    """Enough registered images that the stage writes the model (the stage fails under this)."""
    return registered >= max(MIN_REGISTERED, FAIL_FRACTION * total)


def choose(candidates: Sequence[Candidate], total: int) -> Choice:
    """The attempt to keep (see the module docstring); `candidates` in the order they were made, not empty."""
    if not candidates:
        raise ValueError("expected at least one candidate")
    order = sorted(range(len(candidates)), key=lambda i: (-candidates[i].registered, -candidates[i].points, i))
    sane = [i for i in order if candidates[i].sane and usable(candidates[i].registered, total)]
    pool = [i for i in sane if candidates[i].consistent]
    k = pool[0] if pool else sane[0] if sane else order[0]
    kept = candidates[k]
    head = f"kept '{kept.name}' ({kept.registered}/{total} registered"
    if kept.registered == 0:
        return Choice(index=k, sentence=f"{head}): no attempt registered any image", warning=None)
    if pool:
        # attempts that failed a check and registered as many or more, then the others that failed one
        over = [i for i in order if i != k and i not in pool and candidates[i].registered >= kept.registered]
        under = [i for i in order if i != k and i not in pool and i not in over]
        if not over:
            only = "the only attempt" if len(candidates) == 1 else "the most registered"
            consistent = ", and its poses agree with the photos" if kept.consistency else ""
            sentence = f"{head}, {only}), and its cameras pass the checks{consistent}"
            if under:
                sentence += f"; passed over: {_passed(candidates, under, total)}"
            return Choice(index=k, sentence=sentence, warning=None)
        sentence = (
            f"{head}), whose cameras pass the checks and whose poses agree with the photos, over attempts that "
            f"registered as many or more: {_passed(candidates, over, total)}"
        ) + (f"; also passed over: {_passed(candidates, under, total)}" if under else "")
        return Choice(index=k, sentence=sentence, warning=None)
    if sane:  # sane cameras, but every such model folded: the most registered of them, suspect
        bad = quality.failed(list(kept.consistency))
        why = "every attempt whose cameras pass the checks failed a consistency check"
        return Choice(
            index=k,
            sentence=f"{head}), the most registered with sane cameras, although its poses failed {bad}: {why}",
            warning=f"the kept model's poses failed {bad} ({why}): the poses are likely wrong where faces look alike",
        )
    bad = quality.failed(list(kept.checks), camera_only=True) or "none"
    others = "no other attempt" if len(candidates) > 1 else "no attempt"
    why = f"{others} that registered at least {FAIL_FRACTION:.0%} of the images passes the camera checks"
    if kept.sane:  # it passes, but too few registered: the stage fails on the count
        return Choice(index=k, sentence=f"{head}), the most registered; {why}", warning=None)
    return Choice(
        index=k,
        sentence=f"{head}), the most registered, although its camera failed {bad}: {why}",
        warning=f"the kept model's camera failed {bad}, and {why}: check the intrinsics before trusting the poses",
    )


def _passed(candidates: Sequence[Candidate], passed: list[int], total: int) -> str:
    """ "'a' (22/22) failed focal_vs_exif = 40 (expected <= 25 %) (decided by focal_vs_exif)": the attempts passed
    over for a failed check, and which checks decided."""
    listed = "; ".join(
        f"'{candidates[i].name}' ({candidates[i].registered}/{total}) {_why_not(candidates[i])}" for i in passed
    )
    decided = sorted({_decider(candidates[i]) for i in passed})
    return f"{listed} (decided by {', '.join(decided)})"


def _why_not(c: Candidate) -> str:
    if not c.sane:
        return f"failed {quality.failed(list(c.checks), camera_only=True)}"
    return f"failed {quality.failed(list(c.consistency))}"


def _decider(c: Candidate) -> str:
    """The check(s) that passed over candidate `c`: its failed camera checks, else its failed consistency checks."""
    if not c.sane:
        return ", ".join(x.name for x in c.checks if not x.ok and x.name in quality.CAMERA_CHECKS)
    return ", ".join(x.name for x in c.consistency if not x.ok)


def stop_reason(candidates: Sequence[Candidate], total: int, spent: float, budget: float) -> str | None:
    """Why the ladder stops after the attempts made so far (`spent`: the stage's seconds so far, `budget`: its time
    budget), or None to go on."""
    for c in candidates:
        if c.sane and c.consistent and c.registered >= WARN_FRACTION * total:
            enough = f"{c.registered}/{total} (>= {WARN_FRACTION:.0%})"
            agree = " and its poses agree with the photos" if c.consistency else ""
            return f"'{c.name}' registered {enough}, its cameras pass the checks{agree}"
    kept = keepable(candidates, total)
    if kept is not None and spent >= budget:
        return (
            f"the stage took {spent:.0f} s, its time budget of {budget:.0f} s, and '{kept.name}' is usable "
            f"({kept.registered}/{total} registered, cameras pass the checks, poses consistent)"
        )
    return None


def keepable(candidates: Sequence[Candidate], total: int) -> Candidate | None:
    """The first attempt the stage would keep as it is (usable, sane cameras, consistent poses), or None."""
    return next((c for c in candidates if c.sane and c.consistent and usable(c.registered, total)), None)


def agreement(records: list[dict], models: Sequence[pycolmap.Reconstruction | None], kept: int) -> str:
    """Each other attempt's rotation disagreement with the kept model into its record ("rotation_vs_kept_deg":
    median, largest); a clause for the choice sentence naming those that disagree (over consistency.AGREE_DEG).
    `records` and `models`: one per attempt (None: no model); `kept`: the kept attempt's index."""
    model = models[kept]
    apart = []
    for i, (record, other) in enumerate(zip(records, models, strict=True)):
        if i == kept or other is None or model is None:
            continue
        median, largest, common = rotation_disagreement(model, other)
        if common >= 2:
            record["rotation_vs_kept_deg"] = [round(median, 2), round(largest, 2)]
            if median > AGREE_DEG:
                apart.append(f"'{record['name']}' by {median:.1f} deg (largest {largest:.0f})")
    if not apart:
        return ""
    return (
        "; the attempts disagree on the rotation between two cameras (median over pairs): "
        + ", ".join(apart)
        + " from the kept model"
    )
