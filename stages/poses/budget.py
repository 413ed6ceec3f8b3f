"""The poses stage's time budget: a capture's poses in bounded time, whatever the photos' resolution (issue 53: 22
photos of 4000 x 4000 px took 590 s, most of it in retries at 3200 px with 8192 features).

The budget (`Config.time_budget`; unset: SECONDS_PER_PHOTO x the photos, at least MIN_SECONDS: 110 s for 22
photos) bounds two things, each from times the stage itself measured:
- the first attempt's SIFT working size (`cap_working_size`): the working-size probe extracts 3 photos at each
  size it counts, and is timed; a size whose predicted extraction of the whole set (photos x the probe's seconds a
  photo; a size not probed: the last probed one's x the ratio of pixels) would take over FIRST_EXTRACTION_SHARE
  of the budget is not used: the largest size that fits is, and at least the smallest candidate;
- the retries (`fit_retry`): with a usable model in hand (one the stage would keep: enough registered, cameras and
  poses passing), a retry starts only if its predicted cost fits what is left of the budget. Costs are predicted
  from the first attempt's phases (`AttemptCost`): a new extraction at working size s2 costs its extraction x
  (s2 / s1)^2, matching x (features2 / features1)^2 (exhaustive matching compares every feature of every pair),
  mapping x features2 / features1; features2 = min(cap2, features1 x (s2 / s1)^2). Re-mapping with the relaxed
  mapper costs RELAXED_MAPPING mappings; guided re-matching GUIDED_MATCHING matchings and GUIDED_MAPPING mappings
  (measured, below). An extraction retry ("more features") that does not fit is shrunk first
  (its working size down the candidates to the first attempt's, its cap halved down to the first attempt's
  features): the largest that fits runs; when none does, the retry is left out. Wide-baseline features cost
  WIDE_EXTRACTION x an extraction at their size and find WIDE_FEATURES x its features (capped), matched at
  WIDE_MATCHING x the plain cost of as many; they are never shrunk (made at 1000 px or the first attempt's size).
Without a usable model, every retry runs whatever the budget (the alternative is a failed or a suspect result),
and so does the retry that cures a fold (`consistency`: a mapping of restricted pairs). The budget is wall-clock:
on a loaded machine the same photos get fewer retries. `Config.time_budget = 0` bounds nothing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from nerfpipe.stages.poses.colmap import WORKING_SIZES, SfmSettings

__all__ = [
    "SECONDS_PER_PHOTO",
    "MIN_SECONDS",
    "FIRST_EXTRACTION_SHARE",
    "WIDE_EXTRACTION",
    "WIDE_FEATURES",
    "WIDE_MATCHING",
    "stage_budget",
    "cap_working_size",
    "AttemptCost",
    "predict",
    "fit_retry",
    "attempt_cost",
]

SECONDS_PER_PHOTO = 5.0
"""The default budget per photo: 22 photos in 110 s, 50 in 250 s (the fox's poses take ~25 s, no retry)."""
MIN_SECONDS = 60.0
"""... and never under this: a small set's retries are cheap."""
FIRST_EXTRACTION_SHARE = 1 / 3
"""The first attempt's extraction may take this share of the budget: matching, mapping and a retry need the rest."""
RELAXED_MAPPING = 2.0
GUIDED_MATCHING = 3.0
GUIDED_MAPPING = 20.0
"""The retries that reuse features cost more than the first attempt's phases: the relaxed mapper maps 1-1.6 x as
long (the head, masked: 11.1 s against 11.4 s at 1000 px; 22 photos of 4000 px all round: 11.9 against 7.3 s);
guided matching matches 3 x as long and its many weak pairs make the relaxed mapper's trials 18 x as long (the
same 22: 31.6 s against 10.6 s, 134 s against 7.3 s; the prediction before these factors let it start with 20 s
left and the stage end at 255 s of a 110 s budget)."""


WIDE_EXTRACTION = 7.5
WIDE_FEATURES = 4.0
WIDE_MATCHING = 1.3
"""Wide-baseline features (`colmap.SfmSettings.wide_baseline`) against plain SIFT at the same working size and cap:
SIFT upsampled 2x with DSP and affine shapes extracts 7.5 x as long and finds 4 x the features (the 2x upsampling's
pixels), which guided matching matches in 1.3 x the time plain matching would take on as many (22 photos of the
masked head all round at 1000 px, 2 shared cores: 41 s against 5.5 s, 2,394 against 601 features, 15.6 s against
0.77 s of matching; mapping 2.4 s against 0.33 s, as the features)."""


def stage_budget(asked: float | None, photos: int) -> float:
    """Seconds the stage aims to finish in: `asked` (0: unbounded, inf), else SECONDS_PER_PHOTO x photos, at least
    MIN_SECONDS."""
    if asked is not None:
        return math.inf if asked == 0 else float(asked)
    return max(MIN_SECONDS, SECONDS_PER_PHOTO * photos)


def cap_working_size(
    size: int, seconds_per_photo: dict[int, float], photos: int, budget: float, long_side: int
) -> tuple[int, str | None]:
    """The first attempt's working size: `size` (the smallest with enough features, `colmap.choose_working_size`)
    unless extracting the `photos` at it is predicted to take over FIRST_EXTRACTION_SHARE of `budget`; then the
    largest candidate size whose prediction fits (at least the smallest). `seconds_per_photo`: the probe's
    extraction seconds a photo at each size it counted. Returns (size, why it was capped, or None)."""
    if not seconds_per_photo or math.isinf(budget):
        return size, None
    limit = FIRST_EXTRACTION_SHARE * budget
    candidates = sorted({min(s, long_side) for s in WORKING_SIZES})

    def predicted(s: int) -> float:
        if s in seconds_per_photo:
            return photos * seconds_per_photo[s]
        probed = max(p for p in seconds_per_photo if p <= s) if any(p <= s for p in seconds_per_photo) else None
        base = probed if probed is not None else min(seconds_per_photo)
        return photos * seconds_per_photo[base] * (s / base) ** 2

    if predicted(size) <= limit:
        return size, None
    fits = [s for s in candidates if s < size and predicted(s) <= limit]
    capped = max(fits) if fits else candidates[0]
    why = (
        f"{size} px would take ~{predicted(size):.0f} s to extract ({photos} photos at the probe's "
        f"{predicted(size) / photos:.1f} s a photo), over {FIRST_EXTRACTION_SHARE:.0%} of the {budget:.0f} s budget: "
        f"{capped} px (~{predicted(capped):.0f} s)"
    )
    return capped, why


@dataclass(frozen=True, kw_only=True)
class AttemptCost:
    """What an attempt that extracted features cost, phase by phase (seconds), and what it extracted."""

    size: int
    """Working size (long side, px, at most the photos')."""
    cap: int
    """Its feature cap (max_num_features)."""
    features: float
    """Median features a photo."""
    extraction: float
    matching: float
    mapping: float


def predict(first: AttemptCost, size: int, cap: int, reuse: str, *, wide: bool = False) -> float:
    """Predicted seconds of a retry after `first` (module doc): `reuse` "nothing" (extract at `size` with `cap`;
    `wide`: wide-baseline features, matched guided), "features" (match and map again), "matches" or "neighbours"
    (map again)."""
    pixels = (size / first.size) ** 2
    if wide:
        features = min(cap, first.features * pixels * WIDE_FEATURES) if first.features > 0 else cap
        ratio = features / max(first.features, 1.0)
        return (
            first.extraction * pixels * WIDE_EXTRACTION
            + first.matching * ratio**2 * WIDE_MATCHING
            + first.mapping * ratio
        )
    if reuse == "neighbours":
        return first.mapping
    if reuse == "matches":
        return RELAXED_MAPPING * first.mapping
    if reuse == "features":
        return GUIDED_MATCHING * first.matching + GUIDED_MAPPING * first.mapping
    features = min(cap, first.features * pixels) if first.features > 0 else cap
    ratio = features / max(first.features, 1.0)
    return first.extraction * pixels + first.matching * ratio**2 + first.mapping * ratio


def fit_retry(
    settings: SfmSettings, reuse: str, first: AttemptCost, left: float, long_side: int
) -> tuple[SfmSettings | None, float, str]:
    """The retry to run within `left` seconds: `settings` if its predicted cost fits, an extraction retry shrunk
    until it does (module doc), or None. Returns (settings or None, predicted seconds, what was decided)."""
    cost = predict(
        first, min(settings.max_image_size, long_side), settings.max_num_features, reuse, wide=settings.wide_baseline
    )
    if cost <= left:
        return settings, cost, f"predicted {cost:.0f} s, {left:.0f} s of the budget left"
    if reuse == "nothing" and not settings.wide_baseline:
        for size, cap in _shrunk(settings, first, long_side):
            cost = predict(first, size, cap, reuse)
            if cost <= left:
                shrunk = replace(settings, max_image_size=size, max_num_features=cap)
                return shrunk, cost, f"shrunk to {size} px, {cap} features: predicted {cost:.0f} s, {left:.0f} s left"
    return None, cost, f"left out: predicted {cost:.0f} s, {left:.0f} s of the budget left"


def _shrunk(settings: SfmSettings, first: AttemptCost, long_side: int) -> list[tuple[int, int]]:
    """(working size, cap) of smaller extraction retries that still find more than the first attempt, largest
    first: a larger size (down to the first attempt's), each with the cap halved down to the first attempt's; at
    the first attempt's own size only a larger cap, and only where its cap bound (`colmap`: a larger size under a
    binding cap adds no finer features, a larger cap under one that did not bind adds none)."""
    top = min(settings.max_image_size, long_side)
    sizes = sorted({min(s, long_side) for s in WORKING_SIZES if first.size < min(s, long_side) <= top}, reverse=True)
    caps, cap = [], settings.max_num_features
    while cap >= first.cap:
        caps.append(cap)
        cap //= 2
    out = [(s, c) for s in sizes for c in caps]
    if first.features >= 0.7 * first.cap:  # the first attempt's cap bound: more of the same size's features
        out += [(first.size, c) for c in caps if c > first.cap]
    return out


def attempt_cost(
    settings: SfmSettings, long_side: int, features: Sequence[int], phases: dict[str, float]
) -> AttemptCost:
    """The AttemptCost of an attempt that extracted with `settings` (`features`: each photo's count; `phases`: its
    seconds in "features", "matching", "mapping")."""
    median = sorted(features)[len(features) // 2] if features else 0
    return AttemptCost(
        size=min(settings.max_image_size, long_side),
        cap=settings.max_num_features,
        features=float(median),
        extraction=phases.get("features", 0.0),
        matching=phases.get("matching", 0.0),
        mapping=phases.get("mapping", 0.0),
    )
