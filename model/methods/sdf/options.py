"""The SDF method's options group (`train --method sdf`). A field whose default is None is an automatic default
(`model.methods.sdf.SdfMethod.prepare` resolves it and says why; config.json records the result)."""

from __future__ import annotations

from dataclasses import dataclass

from nerfpipe.data.errors import UserError

__all__ = [
    "SdfOptions",
    "validate_options",
    "RESOLUTION",
    "UPSAMPLE_AT",
    "SAMPLES",
    "REFINE",
    "CURVATURE_REAL",
    "DENSE_GRID",
]

RESOLUTION = (32, 128)
"""The grid's resolution at the start and at the end (coarse-to-fine) by default."""
UPSAMPLE_AT = (0.1, 0.2, 0.3, 0.4)
"""Run fractions of the grid's growth by default (the density method's steps, a little later: the start shape must
first move to the object's hull)."""
SAMPLES = 32
"""Intervals a ray is cut into in the box by default."""
REFINE = 4
"""Sub-intervals each interval of the band is cut into by default."""
DENSE_GRID = 16
"""The dense grid's resolution per axis by default for objects in their box: without it the planes and lines carve a
flat disk out of the starting ellipsoid in axis-aligned stripes of a third to half a cell (docs/SDF.md). Real
captures (contracted scenes) keep 0: on the fox it made the unseen back of the box solid (train's surface_found
check said suspect) for no better held-out PSNR."""
CURVATURE_REAL = 1e-4
"""The curvature term's weight by default in a contracted scene (a real capture): the fox's surface without it is
covered in ripples a few cells across, with it smooth at the same held-out PSNR (docs/SDF.md). Objects in their box
keep 0: at 1e-4 bench-sdf's scene meshed worse (Chamfer 0.33 against 0.21 % of the diagonal, docs/SDF.md)."""


@dataclass(frozen=True, kw_only=True)
class SdfOptions:
    """A signed distance (ellipsoid start + dense grid + VM grid), NeuS's logistic opacity with a learned sharpness,
    Eikonal term."""

    resolution: tuple[int, int] | None = None
    """Grid resolution per axis at the start and at the end (coarse-to-fine). None: 32,128."""
    upsample_at: tuple[float, ...] | None = None
    """Run-progress fractions at which the grid grows (geometric steps to the final size). None: 0.1,0.2,0.3,0.4."""
    sdf_samples: int | None = None
    """Intervals each ray is cut into inside the box (training and rendering). None: 32."""
    sdf_refine: int | None = None
    """Sub-intervals each interval near the surface (the band) is cut into, read with gradient. None: 4."""
    eikonal: float = 0.01
    """Weight of the Eikonal term mean (|grad f| - 1)^2, finite differences one grid cell wide. NeuS's 0.1 is set
    against an L1 colour loss; against train's squared error it flattened the grid to nothing (docs/SDF.md)."""
    init_radius: float = 0.5
    """The starting shape: the ellipsoid inscribed in the box shrunk by this fraction (a sphere in a cube box)."""
    view_dependent: bool | None = None
    """Colour depends on view direction (None: on for every scene; off suits Lambertian scenes)."""
    curvature: float | None = None
    """Weight of Neuralangelo's curvature term, mean |Laplacian f| over the coloured samples (u units, one cell
    wide): smooths the surface. None: 1e-4 for real captures (contracted scenes), 0 (off) for objects in their box."""
    dense_grid: int | None = None
    """Resolution per axis of a dense grid of distances under the planes and lines (trilinear, starting at 0): the
    coarse shape, which the low-rank factors then only refine. None: 16 for objects in their box, 0 (none) for real
    captures (contracted scenes); runs before it had none."""
    outside_tv: float = 0.01
    """Contracted scenes: weight of the total variation on the outside field's planes (the density method's weight
    for real captures); object scenes have no outside field."""


def validate_options(options: SdfOptions) -> None:
    """Every check the options alone allow (UserError naming the option)."""
    if options.resolution is not None and (len(options.resolution) != 2 or min(options.resolution) < 2):
        raise UserError(f"resolution: expected (start, end) >= 2, got {options.resolution}")
    at = options.upsample_at
    if at is not None and (any(not 0 <= a <= 1 for a in at) or list(at) != sorted(at)):
        raise UserError(f"upsample_at: expected increasing fractions in [0, 1], got {at}")
    if options.sdf_samples is not None and options.sdf_samples < 2:
        raise UserError(f"sdf_samples: expected >= 2, got {options.sdf_samples}")
    if options.sdf_refine is not None and options.sdf_refine < 1:
        raise UserError(f"sdf_refine: expected >= 1, got {options.sdf_refine}")
    if not options.eikonal >= 0:
        raise UserError(f"eikonal: expected >= 0, got {options.eikonal}")
    if options.curvature is not None and not options.curvature >= 0:
        raise UserError(f"curvature: expected >= 0, got {options.curvature}")
    if options.dense_grid is not None and options.dense_grid != 0 and options.dense_grid < 2:
        raise UserError(f"dense_grid: expected 0 (none) or >= 2, got {options.dense_grid}")
    if not options.outside_tv >= 0:
        raise UserError(f"outside_tv: expected >= 0, got {options.outside_tv}")
    if not 0 < options.init_radius < 1:
        raise UserError(f"init_radius: expected in (0, 1), got {options.init_radius}")
