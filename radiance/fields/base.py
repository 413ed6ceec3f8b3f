"""The field interface every radiance/attenuation field implements.

Conventions (see docs/DESIGN.md): positions `x` are in the scene frame (world units, the `aabb` of the
scene), directions `d` are unit vectors in the same frame, pointing from the camera into the scene.
`sigma` is a volume density (attenuation coefficient) per world unit, non-negative and finite: the
renderer computes alpha = 1 - exp(-sigma * delta) with delta in world units.

A density-only field (X-ray: Beer-Lambert attenuation, no emission) has `has_color = False`; its
`forward` returns `rgb = None`. A field without view dependence ignores `d` (callers may pass None).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["Field", "check_points"]


def check_points(x: Tensor, name: str = "x") -> None:
    """Public-boundary shape check: x must be [N, 3]."""
    if x.dim() != 2 or x.shape[-1] != 3:
        raise ValueError(f"expected {name} [N, 3], got {tuple(x.shape)}")


class Field(nn.Module):
    """Maps positions (and optionally view directions) to density and colour.

    Subclasses implement `density` and `color`; `forward` combines them. Flags:
    - `has_color`: the field emits colour (False: density-only, e.g. X-ray attenuation),
    - `view_dependent`: colour depends on the viewing direction.
    """

    has_color: bool = True
    view_dependent: bool = True

    def density(self, x: Tensor) -> Tensor:
        """x [N, 3] scene frame -> sigma [N] >= 0, per world unit."""
        raise NotImplementedError

    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        """x [N, 3], d [N, 3] unit (or None when not view dependent) -> rgb [N, 3] in [0, 1]."""
        raise NotImplementedError

    def touch(self) -> None:
        """Say that the parameters changed in place without bumping their version counters (torch's fused Adam does
        not: `p._version` stays put), so that caches keyed on them are rebuilt. No cache here: nothing to do."""

    def forward(self, x: Tensor, d: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """x [N, 3], d [N, 3] | None -> (sigma [N], rgb [N, 3] | None)."""
        check_points(x)
        if d is not None and d.shape != x.shape:
            raise ValueError(f"expected d {tuple(x.shape)}, got {tuple(d.shape)}")
        if self.has_color and self.view_dependent and d is None:
            raise ValueError("this field is view dependent: pass directions d [N, 3]")
        sigma = self.density(x)
        rgb = self.color(x, d) if self.has_color else None
        return sigma, rgb

    def param_groups(self, lr: float) -> list[dict]:
        """Optimizer parameter groups at base learning rate `lr` (fields may scale some groups)."""
        return [{"params": [p for p in self.parameters() if p.requires_grad], "lr": lr, "lr_scale": 1.0}]

    def config(self) -> dict:
        """Primitive constructor arguments that rebuild this field (stored in checkpoints)."""
        raise NotImplementedError

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device
