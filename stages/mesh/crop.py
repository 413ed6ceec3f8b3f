"""What a capture is of: the default box of `stages.mesh` for scenes whose photos see their surroundings.

An object scene (`Space.object_box`: alpha or a plain background) meshes the occupied cells of its occupancy
grid; there the field holds nothing but the object. A real capture (contracted or forward-facing) has walls, a
floor, a table in the field, and its occupied box is the scene box: meshing it gives a slab of wall with the
object as a blob in it (the fox, issue 29). Two rules, measured on the fox:

1. **Looked-at box** (`looked_at_box`): people frame what they capture. Rays through the central window (the
   middle `window` of each side) of every training view are rendered to their median depth (where the ray becomes
   half opaque: the surface it sees); the box of those points, from the `trim` to the 1 - `trim` quantile on each
   axis, grown by `margin` of its size on each side, is the object's box. On the fox (43 views, window 0.5): the
   head, the plaque and a patch of wall behind them.
2. **Support plane** (`support_plane`): the wall, floor or table the object stands on or hangs from. A plane found
   by RANSAC among the looked-at points is the support when it holds at least `min_share` of them, spans the
   looked-at points' extent in both of its directions (it is the surroundings, not a flat face of the object), and
   every camera is on one side of it. The mesh keeps what lies beyond `offset` of the plane on the cameras' side
   (`cut_density`). On the fox: 29 % of the points, spanning 100 % x 100 %, 50 of 50 cameras on one side.

Everything is in the scene frame; the renderer is a callback (`depth_fn`), so this module never sees a model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from nerfpipe.model.run import can
from nerfpipe.radiance.camera import generate_rays
from nerfpipe.stages.mesh.cleanup import vertex_components
from nerfpipe.stages.mesh.field_access import as_np, occupied_box

__all__ = [
    "SUPPORT_CLEARANCE",
    "Plane",
    "default_box",
    "looked_at_points",
    "looked_at_box",
    "support_plane",
    "cut_density",
    "drop_box_cut_pieces",
]

SUPPORT_CLEARANCE = 1.5
"""The support plane's cut keeps what lies beyond this many inlier tolerances on the cameras' side."""

DepthFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(rays_o [R, 3], rays_d [R, 3]) float32 -> median depth [R] (inf where the ray never becomes half opaque)."""


@dataclass(frozen=True)
class Plane:
    """Points x with normal . x + offset = 0; the normal points to the cameras' side."""

    normal: np.ndarray
    """[3] unit normal, towards the cameras."""
    offset: float
    share: float
    """Fraction of the looked-at points within the inlier tolerance."""
    spans: tuple[float, float]
    """Inliers' extent over all points' extent, along the plane's two directions."""
    cameras_on_side: float
    """Fraction of the camera centres on the normal's side."""

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Signed distance of [N, 3] points, positive on the cameras' side."""
        return x @ self.normal + self.offset


def looked_at_points(
    depth_fn: DepthFn, scene, *, window: float = 0.5, per_view: int = 256, chunk: int = 1 << 14
) -> np.ndarray:
    """[N, 3] float64 scene-frame points where the central window's rays of every training view become half
    opaque (rays that never do are dropped). `per_view` rays a view on a square lattice."""
    if not 0 < window <= 1:
        raise ValueError(f"window: expected a fraction in (0, 1], got {window}")
    frames = scene.split("train") or tuple(range(len(scene.frames)))
    n = max(2, int(math.sqrt(per_view)))
    origins, dirs = [], []
    for i in frames:
        intr = scene.frame_intrinsics(i)
        u = torch.linspace(intr.w * (0.5 - window / 2), intr.w * (0.5 + window / 2), n, dtype=torch.float64)
        v = torch.linspace(intr.h * (0.5 - window / 2), intr.h * (0.5 + window / 2), n, dtype=torch.float64)
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        uv = torch.stack([uu.reshape(-1), vv.reshape(-1)], dim=-1)
        o, d = generate_rays(intr, torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64), uv)
        origins.append(o)
        dirs.append(d)
    o, d = torch.cat(origins).float(), torch.cat(dirs).float()
    t = torch.cat([depth_fn(o[a : a + chunk], d[a : a + chunk]).float().cpu() for a in range(0, len(o), chunk)])
    hit = torch.isfinite(t)
    return (o[hit] + t[hit, None] * d[hit]).double().numpy()


def looked_at_box(
    points: np.ndarray, field_box: np.ndarray, *, trim: float = 0.01, margin: float = 0.1
) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) [3] each: the points' `trim`..1-`trim` quantile box grown by `margin` of its size, within
    `field_box` [2, 3]; None with fewer than 64 points or an empty intersection."""
    if len(points) < 64:
        return None
    lo, hi = np.quantile(points, trim, axis=0), np.quantile(points, 1.0 - trim, axis=0)
    grow = margin * (hi - lo)
    lo, hi = np.maximum(lo - grow, field_box[0]), np.minimum(hi + grow, field_box[1])
    return (lo, hi) if (hi > lo).all() else None


def support_plane(
    points: np.ndarray,
    cameras: np.ndarray,
    *,
    tolerance: float,
    min_share: float = 0.2,
    min_span: float = 0.9,
    iterations: int = 500,
    seed: int = 0,
) -> tuple[Plane | None, Plane | None]:
    """(the support plane or None, the best plane found, for the report). `points` [N, 3] the looked-at points
    inside the box, `cameras` [C, 3] the camera centres, `tolerance` the inlier distance (scene units).
    Deterministic (`seed`)."""
    if len(points) < 64:
        return None, None
    rng = np.random.default_rng(seed)
    best_count, best = -1, None
    for _ in range(iterations):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm <= np.finfo(np.float64).eps * max(1.0, float(np.abs(points).max())) ** 2:
            continue
        n = n / norm
        count = int((np.abs(points @ n - n @ a) < tolerance).sum())
        if count > best_count:
            best_count, best = count, (n, -float(n @ a))
    if best is None:
        return None, None
    n, offset = best
    side = cameras @ n + offset
    if (side > 0).mean() < 0.5:  # the normal points to the cameras
        n, offset, side = -n, -offset, -side
    inliers = points[np.abs(points @ n + offset) < tolerance]
    u = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    spans = tuple(float(np.ptp(inliers @ ax) / max(np.ptp(points @ ax), np.finfo(np.float64).tiny)) for ax in (u, v))
    plane = Plane(n, offset, len(inliers) / len(points), spans, float((side > 0).mean()))  # type: ignore[arg-type]
    support = plane.share >= min_share and min(plane.spans) >= min_span and plane.cameras_on_side == 1.0
    return (plane if support else None), plane


def cut_density(density: Callable[[torch.Tensor], torch.Tensor], plane: Plane, keep_beyond: float):
    """The density function with everything within `keep_beyond` of the plane, or behind it, set to 0."""
    normal = torch.as_tensor(plane.normal, dtype=torch.float32)

    def cut(x: torch.Tensor) -> torch.Tensor:
        sigma = density(x)
        keep = x @ normal.to(x.device) + plane.offset > keep_beyond
        return torch.where(keep, sigma, torch.zeros_like(sigma))

    return cut


def drop_box_cut_pieces(
    verts: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray, tolerance: float
) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray]:
    """Remove the connected pieces that the crop box cuts through (a vertex within `tolerance` of a face of the
    box [lo, hi]), except the largest piece: with a looked-at box they are surroundings at its edge (a picture
    frame beside the fox), not the object the views centre on. (verts, faces, the report's step, the removed
    pieces' faces [K, 3] into the given verts: the self-check does not count their surface as missed)."""
    if len(faces) == 0:
        return verts, faces, {"step": "box_cut_pieces", "removed_pieces": 0, "faces": 0}, faces
    n, label = vertex_components(faces, len(verts))
    face_label = label[faces[:, 0]]
    sizes = np.bincount(face_label, minlength=n)
    at_edge = ((verts - lo < tolerance) | (hi - verts < tolerance)).any(axis=1)
    cut = np.zeros(n, bool)
    cut[np.unique(label[at_edge])] = True
    cut[int(np.argmax(sizes))] = False
    keep_face = ~cut[face_label]
    used = np.zeros(len(verts), bool)
    used[faces[keep_face].ravel()] = True
    index = np.cumsum(used) - 1
    why = "pieces the looked-at box cuts through, other than the largest, are surroundings at its edge"
    step = {
        "step": "box_cut_pieces",
        "removed_pieces": int(cut.sum()),
        "removed_faces": int(sizes[cut].sum()),
        "vertices": int(used.sum()),
        "faces": int(keep_face.sum()),
        "why": why,
    }
    return verts[used], index[faces[keep_face]], step, faces[~keep_face]


def default_box(rule: str, trained: Any) -> tuple[np.ndarray, np.ndarray, str, dict, Plane | None]:
    """(lo, hi, the rule in one phrase, the report's `crop` entry, the support plane to cut or None) for the crop
    rule `rule` (auto, looked-at, occupied, field; this module's doc) of a loaded run (`Trained` attributes);
    falls back to the occupied box, saying why, where the looked-at rule finds too little."""
    aabb = as_np(trained.aabb).reshape(2, 3)
    space = getattr(trained, "space", None)  # a run without a scene space (not a field) crops to what it occupies
    if rule == "auto":
        looks = space is not None and not space.object_box and can(trained, "rays")
        rule = "looked-at" if looks else "occupied"
        why = (
            f"auto: a real capture (scene model {space.name}: the photos see surroundings)"
            if looks
            else "auto: an object scene (alpha or a plain background)"
        )
    else:
        why = f"--crop {rule}"
    if rule == "field":
        return aabb[0], aabb[1], "the field's box", {"rule": "field", "why": why}, None
    if rule == "looked-at":
        pts = looked_at_points(lambda o, d: trained.render_rays(o, d, median=True)["depth_median"], trained.scene)
        box = looked_at_box(pts, aabb)
        if box is not None:
            lo, hi = box
            inside = pts[((pts >= lo) & (pts <= hi)).all(axis=1)]
            cams = np.stack([f.world_from_cam[:3, 3] for f in trained.scene.frames])
            tol = 0.01 * float(np.linalg.norm(hi - lo))
            plane, best = support_plane(inside, cams, tolerance=tol)
            info = {
                "rule": "looked-at",
                "why": why,
                "points": len(pts),
                "window": 0.5,
                "quantiles": [0.01, 0.99],
                "margin": 0.1,
                "support_plane": _plane_report(plane, best, tol),
            }
            return lo, hi, "looked-at box" + (", support plane cut" if plane else ""), info, plane
        why += f"; looked-at rule found {len(pts)} surface points (fewer than 64): occupied box instead"
    lo, hi, how = occupied_box(trained)
    return lo, hi, how, {"rule": "occupied", "why": why}, None


def _plane_report(plane: Plane | None, best: Plane | None, tolerance: float) -> dict:
    if best is None:
        return {"cut": False, "why": "no plane found"}
    entry = {
        "cut": plane is not None,
        "normal": best.normal.round(6).tolist(),
        "offset": round(best.offset, 6),
        "share": round(best.share, 4),
        "spans": [round(x, 4) for x in best.spans],
        "cameras_on_side": round(best.cameras_on_side, 4),
        "tolerance": round(tolerance, 6),
        "keep_beyond": round(SUPPORT_CLEARANCE * tolerance, 6),
        "rule": "share >= 0.2, spans >= 0.9 both ways, every camera on one side",
    }
    return entry
