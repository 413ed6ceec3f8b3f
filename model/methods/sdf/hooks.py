"""The SDF method's pieces of training (`model.methods.hooks.Hook`): the Eikonal term and coarse-to-fine growth.

metrics.csv has a fixed set of columns (`stages.train.setup.METRICS`): the residual and the sharpness are in the
manifest (`used.sdf`, `checks`), not in the per-step rows.

- Eikonal: weight x mean (|grad f| - 1)^2 over the step's samples (the render computes it from the same
  finite differences that give the normals: `model.methods.sdf.model`).
- Coarse-to-fine: the density method's `Upsampling` (geometric steps of the grid at run fractions); finite
  differences follow the grid (one cell wide), so early steps see a smooth, wide gradient and later ones detail.
- Outside smoothing (a contracted scene only): the density method's total variation (`TotalVariation`) on the
  outside field's planes.
"""

from __future__ import annotations

from torch import Tensor

from nerfpipe.model.methods.density.hooks import TotalVariation, Upsampling
from nerfpipe.model.methods.hooks import Batch, Hook, LoopState
from nerfpipe.model.methods.sdf.options import SdfOptions

__all__ = ["Eikonal", "hooks_for"]


class Eikonal(Hook):
    """weight x the render's `eikonal` (module doc)."""

    name = "eikonal"

    def __init__(self, weight: float) -> None:
        self.weight = weight

    def loss(self, loop: LoopState, batch: Batch, out: dict[str, Tensor]) -> Tensor | None:
        return self.weight * out["eikonal"] if self.weight > 0 else None


class Curvature(Hook):
    """weight x the render's `curvature`, mean |Laplacian f| (Neuralangelo's curvature term)."""

    name = "curvature"

    def __init__(self, weight: float) -> None:
        self.weight = weight

    def loss(self, loop: LoopState, batch: Batch, out: dict[str, Tensor]) -> Tensor | None:
        return self.weight * out["curvature"] if "curvature" in out else None


def hooks_for(options: SdfOptions, *, outside: bool = False) -> list[Hook]:
    """The method's hooks for resolved `options`, in call order (`outside`: the model has an outside field)."""
    hooks: list[Hook] = [Upsampling(options.resolution, options.upsample_at), Eikonal(options.eikonal)]
    if options.curvature > 0:
        hooks.append(Curvature(options.curvature))
    if outside and options.outside_tv > 0:
        hooks.append(TotalVariation(options.outside_tv, field=lambda model: model.outside.field))
    return hooks
