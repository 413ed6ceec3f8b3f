"""The VM factors as channels-last tables, sampled by `F.embedding_bag`: the fast path of a TensoRF field's
appearance features at inference.

`grid_sample` on a plane [1, C, H, W] reads each channel from its own H x W slice: a bilinear sample touches
2 x C cache lines (two rows a channel). Held as a table of texels [H * W, C], the four corners are four rows of C
contiguous values, and `embedding_bag(mode="sum")` with the bilinear weights as per-sample weights gathers and blends
them in one pass. The three planes share one table (and the three lines another), each point's bags ordered
(point, plane), so one call serves all three and the result is already [N, 3 C] in plane order. Only for factors of
one component count (`fits`): `embedding_bag` runs on one thread, and three calls for a count per plane measured
slower than `grid_sample`. The values are `grid_sample`'s (align_corners, points in [-1, 1]) up to float rounding;
`tests/test_vm_tables.py` checks them, and their gradients, against `radiance.fields.fast._plane_features` (the plain
twin). A table is a copy of the factors: build it once per set of factors (`VmTables.build`), not per call.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["VmTables"]

PLANE_U, PLANE_V = [0, 0, 1], [1, 2, 2]
"""Each plane's (u, v) coordinates (u -> W, v -> H): radiance.fields.fast's PLANE_AXES (0, 1), (0, 2), (1, 2)."""
LINE_W = [2, 1, 0]
"""Each line's coordinate: radiance.fields.fast's LINE_AXIS."""


def _corner(pos: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Texel positions pos (0 .. size - 1) -> (the lower corner, long; the fraction past it). The last interval is
    closed: pos = size - 1 gives corner size - 2 and fraction 1 (size 1: corner 0, fraction 0, no neighbour read)."""
    lower = pos.floor().clamp(0, max(size - 2, 0))
    return lower.long(), pos - lower


@dataclass(frozen=True)
class VmTables:
    """The three planes as one table [3 R R, C] (plane m's texel (v, u) at row m R R + v R + u) and the three lines
    as one table [3 R, C]."""

    planes: Tensor
    lines: Tensor
    resolution: int

    @staticmethod
    def fits(planes: Sequence[Tensor], lines: Sequence[Tensor]) -> bool:
        """Three planes [1, C, R, R] and three lines [1, C, R, 1] of one C and one R: what `build` takes."""
        if len(planes) != 3 or len(lines) != 3:
            return False
        c, r = planes[0].shape[1], planes[0].shape[-1]
        return all(tuple(p.shape[1:]) == (c, r, r) for p in planes) and all(
            tuple(ln.shape[1:]) == (c, r, 1) for ln in lines
        )

    @classmethod
    def build(cls, planes: Sequence[Tensor], lines: Sequence[Tensor]) -> VmTables:
        """From the field's factors: planes (xy, xz, yz) [1, C, R, R], lines (z, y, x) [1, C, R, 1] (copies; gradients
        flow to the factors when they require them). A component count per plane is refused: there three calls of
        `embedding_bag` measured slower than `grid_sample` (docs/TRAINING.md, "Inference")."""
        if not cls.fits(planes, lines):
            raise ValueError(
                "expected three planes [1, C, R, R] and three lines [1, C, R, 1] of one C and one R, got "
                f"{[tuple(p.shape) for p in planes]} and {[tuple(ln.shape) for ln in lines]}"
            )
        r = planes[0].shape[-1]
        plane_rows = torch.cat([p[0].permute(1, 2, 0).reshape(r * r, -1) for p in planes])  # [3 R R, C]
        line_rows = torch.cat([ln[0, :, :, 0].T for ln in lines])  # [3 R, C]
        return cls(plane_rows.contiguous(), line_rows.contiguous(), r)

    def features(self, xn: Tensor) -> Tensor:
        """Box coordinates xn [N, 3] in [-1, 1] -> each plane times its line, [N, 3 C] in plane order (torch.cat of
        `_plane_features`' [C, N] outputs, transposed)."""
        n, r = xn.shape[0], self.resolution
        corner, frac = _corner((xn + 1) * (0.5 * (r - 1)), r)  # [N, 3] per axis: one grid size for all factors
        plane = torch.arange(3, device=xn.device)  # [3]
        cu, cv, cw = corner[:, PLANE_U], corner[:, PLANE_V], corner[:, LINE_W]  # [N, 3] each
        fu, fv, fw = frac[:, PLANE_U], frac[:, PLANE_V], frac[:, LINE_W]
        i = plane * (r * r) + cv * r + cu  # [N, 3] rows of the corners (u, v) below the points
        step = int(r > 1)
        index = torch.stack([i, i + step, i + r * step, i + (r + 1) * step], dim=-1).view(3 * n, 4)  # bags (point, m)
        gu, gv = 1 - fu, 1 - fv
        weights = torch.stack([gu * gv, fu * gv, gu * fv, fu * fv], dim=-1).view(3 * n, 4)
        p = F.embedding_bag(index, self.planes, per_sample_weights=weights, mode="sum")  # [3 N, C]
        k = plane * r + cw  # [N, 3]
        index = torch.stack([k, k + step], dim=-1).view(3 * n, 2)
        weights = torch.stack([1 - fw, fw], dim=-1).view(3 * n, 2)
        line = F.embedding_bag(index, self.lines, per_sample_weights=weights, mode="sum")  # [3 N, C]
        return (p * line).view(n, -1)  # bags (point, plane): [3 N, C] is [N, 3 C] in plane order
