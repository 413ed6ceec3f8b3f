"""Whether a COLMAP model's poses agree with the photos, beyond its own reprojection error (issue 53).

A model reprojects its own 3D points well by construction: the mapper drops every observation that does not fit.
A reconstruction can therefore fold onto itself (photos of two faces that look alike registered as views of one
face) and still report 0.3 px. Three pieces of evidence that the mapper did not optimise look past that:

- **explained matches** (`pair_evidence`, `explained_share`): every verified image pair of the database holds
  inlier matches found by two-view geometry on the photos alone. The model's poses (and cameras) predict where a
  match may lie: on the epipolar line of its partner. The share of the verified inlier matches between registered
  images whose Sampson distance to that line is under EPIPOLAR_PX is what the poses explain of the photos. A
  right model explains nearly all of them (the few false pairs between faces that look alike are contradicted); a
  folded one contradicts the true pairs that cross each fold.
- **capture order** (`order_is_path`, `order_steps`): photos are usually taken in order, round the object or
  along a path, so that consecutive photos (by name) are neighbours: most of them share a verified pair. Where the
  order is such a path, the model's camera path in that order should have no jumps: a step (the rotation between
  two consecutive cameras) over JUMP_FACTOR x the median step and over JUMP_MIN_DEG is a jump; a fold makes one at
  each crease. Nor should it contradict the matches of consecutive photos (`broken_links`): a model that joined
  two parts of the set through a wrong pair does where they meet, even when its steps look even.
- **agreement between attempts** (`rotation_disagreement`): two models of the same photos should agree on the
  rotation between every two cameras (a comparison that needs no alignment). When they do not, at least one is
  wrong, and the evidence above says which.

`neighbour_pairs` gives the pairs to keep when matching is restricted to neighbours in capture order (the cure
for a fold: a face is then only matched with photos taken next to it).
"""

from __future__ import annotations

import itertools
import math
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from nerfpipe.data.checks import Check

__all__ = [
    "EPIPOLAR_PX",
    "JUMP_FACTOR",
    "JUMP_MIN_DEG",
    "PATH_SHARE",
    "PairEvidence",
    "pair_evidence",
    "explained_share",
    "order_is_path",
    "order_steps",
    "jumps",
    "frame_spans",
    "rotation_disagreement",
    "neighbour_pairs",
    "neighbour_window",
    "verified_pairs",
    "creases",
    "contradicted_pairs",
    "broken_links",
    "CONTRADICTED_SHARE",
    "consistency_checks",
    "LOOK_ALIKE_SHARE",
    "AGREE_DEG",
    "restrict_to_neighbours",
]

EPIPOLAR_PX = 4.0
"""A match is explained when its Sampson distance to the epipolar geometry of the model's two poses is under this
many pixels (the model's focal length): the mapper's own cap on a reprojection error (4 px)."""
JUMP_FACTOR = 4.0
JUMP_MIN_DEG = 20.0
"""A step between consecutive photos is a jump when it exceeds both JUMP_FACTOR x the median step and
JUMP_MIN_DEG: a capture moves by similar steps (a turntable by equal ones); a photo left out makes a step of two,
a second ring one step of ~20-40 deg."""
PATH_SHARE = 0.8
"""The name order is a capture path when at least this share of consecutive photos share a verified pair."""
LOOK_ALIKE_SHARE = 0.05
"""Without a capture order: more than this share of the verified inlier matches contradicting the poses is
suspect (a right model of distinct surfaces explains ~99.9 %: the synthetic scene; a folded carton contradicted
7 %, the right model of it 52 %, all of them false pairs between its look-alike faces)."""
CONTRADICTED_SHARE = 0.5
"""A verified pair is contradicted when the model's poses explain under this share of its inlier matches
(`contradicted_pairs`: the report's count, the look-alike share, `broken_links`; a wrong model of the head all round
explained 0-5 % of three consecutive pairs, the right models of the same photos every consecutive pair over 80 %)."""
AGREE_DEG = 2.0
"""Two attempts agree when the median difference of their rotations between two cameras is under this."""


@dataclass(frozen=True, kw_only=True)
class PairEvidence:
    """One verified image pair between two registered images."""

    a: str
    b: str
    inliers: int
    """Verified inlier matches (two-view geometry on the photos)."""
    explained: int
    """Those whose Sampson distance under the model's relative pose is under EPIPOLAR_PX."""


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def sampson_px(x_a: np.ndarray, x_b: np.ndarray, b_from_a: np.ndarray, focal: float) -> np.ndarray:
    """Sampson distance (pixels at `focal`) of normalised matches x_a, x_b [K, 2] to the essential matrix of the
    relative pose `b_from_a` [3, 4] (x_b^T E x_a = 0)."""
    t = b_from_a[:, 3]
    if np.linalg.norm(t) < 1e-12:
        return np.full(len(x_a), np.inf)  # no baseline: no epipolar geometry to test
    e = _skew(t / np.linalg.norm(t)) @ b_from_a[:, :3]
    ha = np.column_stack([x_a, np.ones(len(x_a))])  # [K, 3]
    hb = np.column_stack([x_b, np.ones(len(x_b))])
    ea = ha @ e.T  # [K, 3]: E x_a
    eb = hb @ e  # [K, 3]: E^T x_b
    num = np.einsum("ij,ij->i", hb, ea) ** 2
    den = ea[:, 0] ** 2 + ea[:, 1] ** 2 + eb[:, 0] ** 2 + eb[:, 1] ** 2
    return focal * np.sqrt(num / np.maximum(den, 1e-300))


def pair_evidence(db_path: Path, rec: pycolmap.Reconstruction) -> list[PairEvidence]:
    """Every verified pair of the database `db_path` whose two images `rec` registered, with how many of its
    inlier matches the model's poses explain. `rec` must come from that database (the same image ids)."""
    registered = {i: im for i, im in rec.images.items() if im.has_pose}
    out: list[PairEvidence] = []
    db = pycolmap.Database.open(db_path)
    try:
        keypoints: dict[int, np.ndarray] = {}

        def normalised(image_id: int) -> np.ndarray:
            if image_id not in keypoints:
                cam = rec.cameras[registered[image_id].camera_id]
                keypoints[image_id] = cam.cam_from_img(db.read_keypoints(image_id)[:, :2].astype(np.float64))
            return keypoints[image_id]

        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            m = np.asarray(geometry.inlier_matches)
            if a not in registered or b not in registered or m.size == 0:
                continue
            ia, ib = registered[a], registered[b]
            b_from_a = ib.cam_from_world() * ia.cam_from_world().inverse()
            focal = 0.5 * (
                rec.cameras[ia.camera_id].mean_focal_length() + rec.cameras[ib.camera_id].mean_focal_length()
            )
            err = sampson_px(normalised(a)[m[:, 0]], normalised(b)[m[:, 1]], b_from_a.matrix(), focal)
            out.append(PairEvidence(a=ia.name, b=ib.name, inliers=len(m), explained=int((err < EPIPOLAR_PX).sum())))
    finally:
        db.close()
    return out


def explained_share(evidence: Sequence[PairEvidence]) -> float:
    """Share of the verified inlier matches (between registered images) that the model's poses explain."""
    total = sum(p.inliers for p in evidence)
    return sum(p.explained for p in evidence) / total if total else math.nan


def order_is_path(names: Sequence[str], verified: set[frozenset[str]]) -> bool:
    """Whether the photos in `names` order (their natural name order) form a capture path: PATH_SHARE of
    consecutive photos share a verified pair (`verified`: the pairs, as frozensets of two names)."""
    if len(names) < 4:
        return False
    linked = sum(frozenset(p) in verified for p in itertools.pairwise(names))
    return linked >= PATH_SHARE * (len(names) - 1)


def _world_from_cam_rotation(image: pycolmap.Image) -> np.ndarray:
    return image.cam_from_world().rotation.matrix().T


def _angle_deg(r: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def order_steps(rec: pycolmap.Reconstruction, names: Sequence[str]) -> list[tuple[str, str, float]]:
    """(name, next name, rotation between the two cameras in degrees) for consecutive registered photos in
    `names` order (a photo the model left out is skipped: its neighbours make one step)."""
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    seq = [n for n in names if n in by_name]
    rot = {n: _world_from_cam_rotation(by_name[n]) for n in seq}
    return [(a, b, _angle_deg(rot[a].T @ rot[b])) for a, b in itertools.pairwise(seq)]


def jumps(steps: Sequence[tuple[str, str, float]]) -> tuple[list[tuple[str, str, float]], float]:
    """(the steps that are jumps, the median step in degrees). A step across a gap in the photos' frame numbers
    (`frame_spans`: 0097.jpg -> 0103.jpg where the others go by 2) may be as many median steps longer: the fox's
    photos are every other frame of a walk with some left out, and a 28 deg step over 6 frames is no fold."""
    if not steps:
        return [], math.nan
    median = float(np.median([s for _, _, s in steps]))
    spans = frame_spans([(a, b) for a, b, _ in steps])
    return [s for s, k in zip(steps, spans, strict=True) if s[2] > max(JUMP_FACTOR * median * k, JUMP_MIN_DEG)], median


_FRAME_NUMBER = re.compile(r"^(.*?)(\d+)\D*$")


def frame_spans(pairs: Sequence[tuple[str, str]]) -> list[float]:
    """How many typical steps each consecutive pair of photo names spans, from the frame number in their names
    (the last digits of the stem): the pair's number gap over the median gap, at least 1. All 1 when a name has
    no number or the prefixes differ (no frame numbering to read)."""
    parsed = [(_FRAME_NUMBER.match(Path(a).stem), _FRAME_NUMBER.match(Path(b).stem)) for a, b in pairs]
    if not parsed or any(x is None or y is None or x.group(1) != y.group(1) for x, y in parsed):
        return [1.0] * len(pairs)
    gaps = [abs(int(y.group(2)) - int(x.group(2))) for x, y in parsed]
    typical = float(np.median(gaps))
    if typical <= 0:
        return [1.0] * len(pairs)
    return [max(1.0, g / typical) for g in gaps]


def rotation_disagreement(a: pycolmap.Reconstruction, b: pycolmap.Reconstruction) -> tuple[float, float, int]:
    """(median, largest) difference in degrees between the two models' rotations between every two cameras both
    registered (no alignment needed), and the number of common images; (nan, nan, n) under 2 common images."""
    ra = {im.name: _world_from_cam_rotation(im) for im in a.images.values() if im.has_pose}
    rb = {im.name: _world_from_cam_rotation(im) for im in b.images.values() if im.has_pose}
    common = sorted(set(ra) & set(rb))
    if len(common) < 2:
        return math.nan, math.nan, len(common)
    diffs = [_angle_deg((ra[i].T @ ra[j]).T @ (rb[i].T @ rb[j])) for i, j in itertools.combinations(common, 2)]
    return float(np.median(diffs)), float(np.max(diffs)), len(common)


def neighbour_window(count: int) -> int:
    """Photos on each side that a photo is matched with when matching is restricted to capture order: an eighth of
    the set (about 45 deg of a turn all round), at least 3."""
    return max(3, count // 8)


def neighbour_pairs(names: Sequence[str], window: int, closed: bool = True) -> set[frozenset[str]]:
    """The pairs within `window` places of one another in `names` order; `closed`: the last photos are also
    neighbours of the first (a capture all round)."""
    n = len(names)
    pairs = set()
    for i in range(n):
        for k in range(1, window + 1):
            j = i + k
            if j < n or (closed and j - n < i):
                pairs.add(frozenset((names[i], names[j % n])))
    return pairs


def verified_pairs(db_path: Path) -> dict[frozenset[str], int]:
    """{frozenset of the two image names: verified inlier matches} for every verified pair of a database."""
    db = pycolmap.Database.open(db_path)
    try:
        name_of = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    out = {}
    for pair_id, n in zip(pair_ids, inliers, strict=True):
        if n > 0:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            out[frozenset((name_of[a], name_of[b]))] = int(n)
    return out


def creases(
    rec: pycolmap.Reconstruction, order: Sequence[str], verified: dict[frozenset[str], int]
) -> tuple[list[tuple[str, str, float, int]], float]:
    """The folds of a model along the capture order: (name, next name, degrees apart, verified matches) for each
    jump (`jumps`) between consecutive photos that share a verified pair: photos taken one after the other and
    seeing the same thing, which the model puts far apart. Also the median step (degrees)."""
    found, median = jumps(order_steps(rec, order))
    return [(a, b, s, verified[frozenset((a, b))]) for a, b, s in found if frozenset((a, b)) in verified], median


def contradicted_pairs(evidence: Sequence[PairEvidence]) -> list[PairEvidence]:
    """The verified pairs whose inlier matches the model's poses mostly contradict (under CONTRADICTED_SHARE
    explained)."""
    return [p for p in evidence if p.explained < CONTRADICTED_SHARE * p.inliers]


def broken_links(
    rec: pycolmap.Reconstruction, order: Sequence[str], contradicted: Sequence[PairEvidence]
) -> list[tuple[str, str, int, float]]:
    """Consecutive registered photos in capture `order` (`order_steps`) whose verified pair is among the
    `contradicted` ones (`contradicted_pairs`): (name, next name, verified matches, share of them explained). Photos
    taken one after the other see the same surface, so their matches are the surest evidence of the path; a model
    that attached part of the set through a wrong pair (22 photos all round a masked head: two arcs joined 30 deg
    off) contradicts the true matches where the arcs meet, even where its steps look even."""
    by_pair = {frozenset((p.a, p.b)): p for p in contradicted}
    out = []
    for a, b, _ in order_steps(rec, order):
        p = by_pair.get(frozenset((a, b)))
        if p is not None:
            out.append((a, b, p.inliers, p.explained / p.inliers))
    return out


def consistency_checks(
    rec: pycolmap.Reconstruction, db_path: Path, order: Sequence[str]
) -> tuple[list[Check], dict[str, Any]]:
    """The checks of a model against the photos' matches (module docstring) and their record for the report.

    `db_path`: the database with every verified pair the photos gave (for an attempt restricted to neighbours, the
    database it was restricted from); `order`: every image name in capture (natural name) order.
    capture_order (when the order is a path): no crease (`creases`). look_alike_matches (when it is not): at most
    LOOK_ALIKE_SHARE of the verified inlier matches contradict the poses, since without an order nothing tells a
    fold from faces that look alike. The explained share is recorded either way."""
    verified = verified_pairs(db_path)
    evidence = pair_evidence(db_path, rec)
    share = explained_share(evidence)
    contradicted = contradicted_pairs(evidence)
    record: dict[str, Any] = {
        "explained_matches": None if math.isnan(share) else round(share, 4),
        "contradicted_pairs": len(contradicted),
        "verified_pairs": len(evidence),
        "order_is_path": order_is_path(order, set(verified)),
    }
    checks: list[Check] = []
    if record["order_is_path"] and rec.num_reg_images() >= 4:
        folds, median = creases(rec, order, verified)
        folded = {frozenset((a, b)) for a, b, _, _ in folds}
        broken = [link for link in broken_links(rec, order, contradicted) if frozenset(link[:2]) not in folded]
        record.update(
            median_step_deg=round(median, 2),
            creases=[[a, b, round(s, 1), n] for a, b, s, n in folds],
            broken_links=[[a, b, n, round(e, 3)] for a, b, n, e in broken],
        )
        where = "; ".join(
            [f"{a} and {b} share {n} verified matches but are {s:.0f} deg apart" for a, b, s, n in folds[:3]]
            + [f"{a} and {b} share {n} verified matches, {e:.0%} of them explained" for a, b, n, e in broken[:3]]
        )
        says = (
            f"{len(folds) + len(broken)} place(s) where consecutive photos that see the same thing are placed far "
            f"apart (over {JUMP_FACTOR:g} x the median step of {median:.1f} deg and {JUMP_MIN_DEG:g} deg) or so that "
            f"their matches contradict the poses (under {CONTRADICTED_SHARE:.0%} explained): {where}: the "
            "reconstruction folded onto itself or joined parts of the set through a wrong pair: faces that look "
            "alike were matched to one another, or (the object on a turntable) a background that did not turn "
            "with it was; mask the background (--masks) if so"
            if folds or broken
            else f"the camera path in capture order has no fold (median step {median:.1f} deg) and explains the "
            "matches of consecutive photos"
        )
        checks.append(Check.upper("capture_order", len(folds) + len(broken), 0, says=says))
    elif evidence:
        bad = sum(p.inliers for p in contradicted) / max(sum(p.inliers for p in evidence), 1)
        record["contradicted_share"] = round(bad, 4)
        says = (
            f"{len(contradicted)} verified image pairs ({bad:.0%} of the matches) contradict the poses, and the "
            "photos' names give no capture order to tell a reconstruction folded onto itself from faces that look "
            "alike; name the photos in the order they were taken (poses then checks the path)"
            if bad > LOOK_ALIKE_SHARE
            else f"the poses explain {share:.1%} of the verified matches"
        )
        checks.append(Check.upper("look_alike_matches", bad * 100, LOOK_ALIKE_SHARE * 100, unit=" %", says=says))
    return checks, record


def restrict_to_neighbours(src: Path, dst: Path, order: Sequence[str]) -> tuple[int, int, int]:
    """A copy `dst` of database `src` whose verified pairs are only those within `neighbour_window` places in
    capture `order` (closed: the last photos neighbour the first). Returns (pairs kept, pairs dropped, window)."""
    shutil.copyfile(src, dst)
    window = neighbour_window(len(order))
    keep = neighbour_pairs(order, window)
    db = pycolmap.Database.open(dst)
    kept = dropped = 0
    try:
        name_of = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        for pair_id, n in zip(pair_ids, inliers, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            if frozenset((name_of[a], name_of[b])) in keep:
                kept += int(n > 0)
            else:
                db.delete_two_view_geometry(a, b)
                dropped += int(n > 0)
    finally:
        db.close()
    return kept, dropped, window
