"""The cure for a model that folds on what does not turn with the object: drop the features matched far across
the capture order (issue 53).

On a turntable shot as is (no masks), the room stands still while the object turns: its features match between
every two photos, however far apart, and the mapper has to explain two motions at once. It folds (the shared head
as shot: 66 of 66 registered, 8.4 deg median / 106 deg largest rotation error, and the neighbours in capture order
folded the same way). Its object, seen from around, matches only photos taken near one another: SIFT loses a
surface turned by more than ~45 deg. A feature with a verified match in a photo over `neighbour_window` places away
(an eighth of the set) in capture order is therefore what did not turn (the static room), or a face that looks
like another (a print repeated on a carton's sides): `far_matched` finds them; `drop_far_matched` writes a database
whose matches that touch them are gone, verified again. Places are counted round a closed loop (`neighbour_pairs`:
the last photos neighbour the first), so an object matched across the loop's seam is kept; an open arc counted
that way only loses the far pairs across its ends, while a static background still matches at every other
distance.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap

from nerfpipe.stages.poses.consistency import neighbour_pairs, neighbour_window

__all__ = ["far_matched", "drop_far_matched"]


def far_matched(db: pycolmap.Database, order: Sequence[str]) -> tuple[dict[int, np.ndarray], int]:
    """({image id: bool [num_keypoints], True where the keypoint has a verified inlier match in a photo more than
    the window's places away round the capture `order`}, the window). Images not in `order` get no far pairs."""
    window = neighbour_window(len(order))
    near, named = neighbour_pairs(order, window), set(order)
    images = db.read_all_images()
    name_of = {im.image_id: im.name for im in images}
    far = {im.image_id: np.zeros(db.num_keypoints_for_image(im.image_id), bool) for im in images}
    pair_ids, geometries = db.read_two_view_geometries()
    for pair_id, geometry in zip(pair_ids, geometries, strict=True):
        m = np.asarray(geometry.inlier_matches)
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        pair = frozenset((name_of[a], name_of[b]))
        if m.size == 0 or not pair <= named or pair in near:
            continue
        far[a][m[:, 0]] = True
        far[b][m[:, 1]] = True
    return far, window


def drop_far_matched(
    src: Path, dst: Path, order: Sequence[str], verify: pycolmap.TwoViewGeometryOptions, num_threads: int = -1
) -> dict:
    """A copy `dst` of database `src` (features matched, pairs verified) whose raw matches that touch a far-matched
    keypoint (`far_matched`) are deleted and whose pairs are verified again with `verify` on `num_threads` threads
    (-1: all). Returns its record: the window, the share of keypoints dropped, the raw matches kept and dropped,
    the verified pairs before and after."""
    shutil.copyfile(src, dst)
    db = pycolmap.Database.open(dst)
    try:
        far, window = far_matched(db, order)
        pairs_before = db.num_verified_image_pairs()
        kept = dropped = 0
        pair_ids, matches = db.read_all_matches()
        for pair_id, m in zip(pair_ids, matches, strict=True):
            m = np.asarray(m)
            if m.size == 0:
                continue
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            keep = ~(far[a][m[:, 0]] | far[b][m[:, 1]])  # [K]
            kept += int(keep.sum())
            dropped += int((~keep).sum())
            if keep.all():
                continue  # nothing to drop: the pair's matches stay as they are
            db.delete_matches(a, b)
            if keep.any():
                db.write_matches(a, b, np.ascontiguousarray(m[keep], dtype=np.uint32))
        db.clear_two_view_geometries()
    finally:
        db.close()
    threads = pycolmap.GeometricVerifierOptions()
    threads.num_threads = num_threads
    pycolmap.geometric_verification(dst, verifier_options=threads, two_view_geometry_options=verify)
    db = pycolmap.Database.open(dst)
    try:
        pairs_after = db.num_verified_image_pairs()
    finally:
        db.close()
    flags = np.concatenate(list(far.values())) if far else np.zeros(0, bool)
    return {
        "window": window,
        "keypoints_dropped_share": round(float(flags.mean()), 4) if flags.size else 0.0,
        "matches_kept": kept,
        "matches_dropped": dropped,
        "verified_pairs_before": int(pairs_before),
        "verified_pairs_after": int(pairs_after),
    }
