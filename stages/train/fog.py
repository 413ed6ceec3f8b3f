"""How much of the space the training cameras see is occupied: the evidence of the train check `occupied_share`.

A fog of density (the background learned as density: issue 27) fills the space in front of every camera; a sound
object field leaves that space empty. The occupancy grid the march uses cannot say which: it is conservative by
design (each cell keeps the largest density seen, decayed by 0.95 at the quarter of the cells refreshed every 16
steps: nerfacc's schedule), so a cell the field emptied late stays marked for hundreds of steps, and cells no
camera sees (inside objects, under a disk seen from above) keep what the initialisation put there. On `make
demo`'s sound 1,000-step run the grid had 64 % of its cells marked, a false "fog"; the field itself, asked at the
end, is over the grid's threshold in 21 % of all cells and 16 % of those the cameras see.

So the share is the field's own, measured at the end: a cell is occupied when the largest density at
POINTS_PER_CELL uniform random points in it exceeds the grid's threshold, and the share is taken over the cells
some training camera sees: a cell is seen by a view when its centre projects into the view's per-view render
(`report.per_view_report`, low resolution) and lies no farther along its pixel's ray than the rendered surface
(the expected depth of a ray whose opacity reaches 1/2; any distance on a ray that stays under 1/2: it sees
through) plus SEEN_TOLERANCE_CELLS cell diagonals.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from nerfpipe.radiance.camera import Intrinsics, project
from nerfpipe.radiance.occupancy import OccupancyGrid

__all__ = ["ViewDepth", "seen_cells", "seen_occupied_share", "SEEN_TOLERANCE_CELLS"]

SEEN_TOLERANCE_CELLS = 1.0
"""A cell behind the rendered surface by up to this many cell diagonals still counts as seen (its surface cell)."""
POINTS_PER_CELL = 4
"""Random points per cell at which the field's density is asked (the grid's own full refresh uses as many)."""
MAX_VIEWS = 48
"""Views asked at most (evenly spaced): each projects every cell (64^3 cells and 43 views: 0.6 s on 2 cores)."""
SEES_THROUGH = 0.5
"""A ray whose opacity stays under this sees through: every cell along it counts as seen."""


@dataclass(frozen=True, kw_only=True)
class ViewDepth:
    """One rendered view: its intrinsics, camera (OpenGL [4, 4]) and per-pixel depth (the expected distance along
    the unit ray, sum(w t) / sum(w), as the renderers give it) and opacity [h, w]."""

    intr: Intrinsics
    world_from_cam: np.ndarray
    depth: np.ndarray
    acc: np.ndarray

    def __post_init__(self):
        shape = (self.intr.h, self.intr.w)
        if self.depth.shape != shape or self.acc.shape != shape:
            raise ValueError(f"expected depth and acc {shape}, got {self.depth.shape} and {self.acc.shape}")


def seen_cells(centres: torch.Tensor, views: list[ViewDepth] | tuple[ViewDepth, ...], tolerance: float) -> torch.Tensor:
    """Cell centres [M, 3] (scene frame) -> bool [M]: seen by at least one view (module docstring; at most
    MAX_VIEWS of them, evenly spaced); `tolerance` is in scene units."""
    if centres.ndim != 2 or centres.shape[-1] != 3:
        raise ValueError(f"expected centres [M, 3], got {tuple(centres.shape)}")
    seen = torch.zeros(centres.shape[0], dtype=torch.bool)
    x = centres.to(torch.float64)
    picked = np.unique(np.linspace(0, len(views) - 1, MAX_VIEWS).round().astype(int)) if views else []
    for v in (views[i] for i in picked):
        c2w = torch.as_tensor(v.world_from_cam, dtype=torch.float64)
        uv, z = project(x, c2w, v.intr)
        col, row = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        inside = (z > 0) & (col >= 0) & (col < v.intr.w) & (row >= 0) & (row < v.intr.h)
        pix = (row.clamp(0, v.intr.h - 1) * v.intr.w + col.clamp(0, v.intr.w - 1))[inside]
        acc = torch.as_tensor(v.acc, dtype=torch.float64).reshape(-1)[pix]
        depth = torch.as_tensor(v.depth, dtype=torch.float64).reshape(-1)[pix]
        surface = torch.where(acc >= SEES_THROUGH, depth, torch.inf)  # depth: sum(w t) / acc, the renderers'
        distance = torch.linalg.norm(x[inside] - c2w[:3, 3], dim=-1)
        seen[torch.nonzero(inside).squeeze(-1)[distance <= surface + tolerance]] = True
    return seen


def seen_occupied_share(
    grid: OccupancyGrid,
    density: Callable[[torch.Tensor], torch.Tensor],
    views: list[ViewDepth] | tuple[ViewDepth, ...],
    *,
    seed: int = 0,
    chunk: int = 1 << 18,
) -> float | None:
    """The share of the grid's cells seen by the views where the field's `density` (x [N, 3] -> sigma [N], scene
    frame: the grid must live there, a `radiance.space.Box`) is over the grid's threshold (module docstring);
    None where no view sees a cell."""
    g = grid.resolution
    idx = torch.arange(g, dtype=torch.float64)
    ijk = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), dim=-1).reshape(-1, 3)  # [G^3, 3]
    lo, cell = grid.aabb[0].to(torch.float64).cpu(), grid.cell_size.to(torch.float64).cpu()
    seen = seen_cells(lo + (ijk + 0.5) * cell, views, SEEN_TOLERANCE_CELLS * float(torch.linalg.norm(cell)))
    if not bool(seen.any()):
        return None
    ijk = ijk[seen]  # [S, 3]
    gen = torch.Generator().manual_seed(seed)
    device = grid.aabb.device
    sigma = torch.zeros(ijk.shape[0], dtype=torch.float32)  # [S]
    for _ in range(POINTS_PER_CELL):
        x = (lo + (ijk + torch.rand(ijk.shape, generator=gen, dtype=torch.float64)) * cell).float()  # [S, 3]
        got = torch.cat(
            [density(x[i : i + chunk].to(device)).reshape(-1).float().cpu() for i in range(0, len(x), chunk)]
        )
        sigma = torch.maximum(sigma, torch.where(torch.isnan(got), torch.inf, got))  # NaN counts as occupied
    return float((sigma > grid.threshold).float().mean())
