"""The density method's options group (`train --method density`, the default): the TensoRF-style field's grid,
march and priors. A field whose default is None is an automatic default, resolved per kind of scene space
(`model.methods.density.rules`, applied by `model.methods.density.defaults`); config.json records the result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from nerfpipe.data.errors import UserError
from nerfpipe.radiance.fields.fast import DENSITY_ACTIVATIONS, split_rank

__all__ = ["DensityOptions", "validate_options"]


@dataclass(frozen=True, kw_only=True)
class DensityOptions:
    """The density field's grid, march and priors (TensoRF VM + occupancy grid)."""

    resolution: tuple[int, int] | None = None
    """Grid resolution per axis at the start and at the end (coarse-to-fine upsampling). None: the scene kind's
    rule (`model.methods.density.rules`): objects and contracted scenes from the object's size in pixels,
    forward-facing (NDC) scenes from the image's width."""
    rank: tuple[int, ...] | None = None
    """The VM field's components per plane (`radiance.fields.fast.TensoRF`): density and appearance, alike on every
    plane (2 counts), or each plane's own (6: density on the xy, xz, yz planes, then appearance). None: the scene
    kind's rule: TensoRF's 16,48 for objects and contracted scenes, TensoRF's LLFF 16,4,4,48,12,12 for
    forward-facing (NDC) scenes (the xy plane is the image plane)."""
    upsample_at: tuple[float, ...] | None = None
    """Run-progress fractions at which the grid is upsampled (geometric steps to the final size). None:
    0.05,0.1,0.2,0.3; with pose refinement 0.2,0.3,0.4,0.5 (coarse-to-fine)."""
    step_ratio: float | None = None
    """Marching step in voxels of the final grid (None: the scene kind's rule: objects 2 below a 200 grid, else 1;
    contracted 2 on CPU; NDC a fixed number of steps across inverse depth)."""
    render_step_factor: float = 0.5
    """Evaluation and rendering march at this fraction of the training step (the field is continuous: finer
    quadrature at inference costs only render time; docs/DENSITY_RULES.md)."""
    occupancy_resolution: int = 64
    """Occupancy grid cells per axis."""
    occupancy_every: int = 16
    """Update the occupancy grid every this many steps."""
    density_l1: float = 0.0
    """Weight of the L1 sparsity prior on the density factors."""
    tv: float | None = None
    """Weight of TensoRF's total-variation prior on the field's planes (`TensoRF.tv`; TensoRF's LLFF setting is
    0.01). None: the scene kind's rule: 0.01 for contracted scenes (real captures, where a VM field otherwise paints
    streaks and floaters into sparsely seen space), NDC's own measured weight, 0 for box scenes (objects)."""
    density_activation: Literal["softplus", "relu"] | None = None
    """The field's density activation (`radiance.fields.fast.TensoRF`): softplus (shift -10) or relu. None: the scene
    kind's rule: relu for forward-facing (NDC) scenes (TensoRF's LLFF setting), softplus for objects and contracted
    scenes."""
    mlp_width: int | None = None
    """Width of the colour MLP's two hidden layers (`radiance.fields.fast.TensoRF`'s hidden). None: the scene kind's
    rule: 64 for every kind (`radiance.fields.fast.DEFAULT_HIDDEN`)."""
    depth_loss: float | None = None
    """Contracted scenes: weight of DS-NeRF's depth loss on rays through the sparse points each training photo
    observed (transforms.json's `sparse_depth_path`, written by `convert` from COLMAP; data.sparse_depth). None:
    `model.methods.density.defaults.DEPTH_LOSS` when the scene has them and is contracted, else 0 (and the manifest
    says why)."""
    distortion: float = 0.0
    """Contracted scenes: weight of mip-NeRF 360's distortion loss (its lambda is 0.01), which pulls each ray's
    weight into one compact peak (radiance.regularizers). Off by default (no gain measured on the fox at 300 s)."""
    view_dependent: bool | None = None
    """Colour depends on view direction (None: on for every scene; off suits Lambertian scenes)."""


def validate_options(options: DensityOptions) -> None:
    """The grid, march and prior weights (UserError naming the option), before any file is read."""
    if options.resolution is not None and (len(options.resolution) != 2 or min(options.resolution) < 2):
        raise UserError(f"expected resolution (start, end) >= 2, got {options.resolution}")
    act = options.density_activation
    if act is not None and act not in DENSITY_ACTIVATIONS:
        raise UserError(f"unknown density activation {act!r}: expected one of {', '.join(DENSITY_ACTIVATIONS)}")
    if options.mlp_width is not None and options.mlp_width < 1:
        raise UserError(f"mlp_width: expected >= 1, got {options.mlp_width}")
    if options.rank is not None:
        try:
            split_rank(options.rank)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    at = options.upsample_at
    if at is not None and (any(not 0 <= a <= 1 for a in at) or list(at) != sorted(at)):
        raise UserError(f"expected upsample_at: increasing fractions in [0, 1], got {at}")
    if not ((options.step_ratio is None or options.step_ratio > 0) and 0 < options.render_step_factor <= 1):
        raise UserError(
            f"expected step_ratio > 0 and 0 < render_step_factor <= 1, got {options.step_ratio}, "
            f"{options.render_step_factor}"
        )
    if options.occupancy_resolution < 1 or options.occupancy_every < 1:
        raise UserError(
            f"expected occupancy_resolution >= 1 and occupancy_every >= 1, got "
            f"{options.occupancy_resolution}, {options.occupancy_every}"
        )
    for name in ("distortion", "density_l1"):
        if not getattr(options, name) >= 0:
            raise UserError(f"expected {name} >= 0, got {getattr(options, name)}")
    for name in ("tv", "depth_loss"):
        value = getattr(options, name)
        if value is not None and not value >= 0:
            raise UserError(f"{name}: expected >= 0, got {value}")
