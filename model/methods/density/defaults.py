"""The density method's automatic defaults, each with its reason for the manifest's `used.defaults`.

- **Grid, march, components, density activation, MLP width and TV per kind of scene**: `model.methods.density.rules`
  (box, contracted and NDC scenes, each rule with the captures it was measured on); a value given wins.
- **Pose refinement** (`train --refine-poses`): coarse-to-fine as BARF anneals its frequencies, in the grid's terms
  (its resolution is its frequency band): the grid starts at a quarter of the final size (at least 16) and is
  upsampled at `REFINE_UPSAMPLE_AT` instead of `UPSAMPLE_AT`, so the cameras first register to a smooth field
  (docs/DENSITY_RULES.md).
- **Depth loss**: DEPTH_LOSS where the scene has sparse points (COLMAP's, through `convert`) and is contracted,
  else 0, and the reason says why.
- **View dependence**: on unless asked off.
"""

from __future__ import annotations

import dataclasses

from nerfpipe.data.errors import UserError
from nerfpipe.data.sparse_depth import KEY as SPARSE_KEY
from nerfpipe.data.transforms import Scene
from nerfpipe.model.methods.base import TrainContext
from nerfpipe.model.methods.density.options import DensityOptions
from nerfpipe.model.methods.density.rules import RULES, BoxRules, NDCRules, Need
from nerfpipe.model.views import DepthRays, sparse_depth_rays
from nerfpipe.radiance.space import Space

__all__ = ["UPSAMPLE_AT", "REFINE_UPSAMPLE_AT", "DEPTH_LOSS", "resolve_options"]

UPSAMPLE_AT = (0.05, 0.1, 0.2, 0.3)
"""Run-progress fractions of the grid upsamplings."""
REFINE_UPSAMPLE_AT = (0.2, 0.3, 0.4, 0.5)
"""The same with pose refinement: the grid stays coarse while the cameras move most."""
DEPTH_LOSS = 0.01
"""Default depth-loss weight where sparse points exist (contracted scenes)."""


def resolve_options(
    options: DensityOptions, ctx: TrainContext, space: Space, reasons: dict[str, str]
) -> tuple[DensityOptions, DepthRays | None]:
    """`options` with every None resolved for `space` (its kind's rules), and the rays of the depth loss (None when
    it is off); each reason in `reasons`. UserError when a depth-loss weight is given that the scene cannot take."""
    need = Need(
        scene=ctx.scene,
        space=space,
        train_idx=tuple(ctx.train_idx),
        downscale=ctx.downscale,
        cuda=ctx.cuda,
        refine_poses=ctx.refine_poses,
    )
    options = _grid_options(options, RULES[type(space)], need, reasons)
    rays, options = _depth_loss(options, ctx.scene, need.train_idx, space, reasons)
    view_dependent = True if options.view_dependent is None else options.view_dependent
    return dataclasses.replace(options, view_dependent=view_dependent), rays


def _grid_options(
    options: DensityOptions, rules: BoxRules | NDCRules, need: Need, reasons: dict[str, str]
) -> DensityOptions:
    """The grid, schedule, step, TV, components, activation and MLP width: as given, else the scene kind's rules."""
    resolution, upsample_at = _grid(options, rules, need, reasons)
    if options.step_ratio is not None:
        step_ratio, reasons["step_ratio"] = float(options.step_ratio), "asked for"
    else:
        step_ratio, reasons["step_ratio"] = rules.step_ratio(resolution, need)
    tv, reasons["tv"] = (float(options.tv), "given") if options.tv is not None else rules.tv()
    rank, reasons["rank"] = (tuple(options.rank), "asked for") if options.rank is not None else rules.rank()
    act = options.density_activation
    act, reasons["density_activation"] = (act, "asked for") if act is not None else rules.density_activation()
    width = options.mlp_width
    width, reasons["mlp_width"] = (width, "asked for") if width is not None else rules.mlp_width()
    return dataclasses.replace(
        options,
        resolution=resolution,
        rank=rank,
        upsample_at=upsample_at,
        step_ratio=step_ratio,
        tv=tv,
        density_activation=act,
        mlp_width=width,
    )


def _grid(
    options: DensityOptions, rules: BoxRules | NDCRules, need: Need, reasons: dict[str, str]
) -> tuple[tuple[int, int], tuple[float, ...]]:
    """The grid's start and final resolution and its upsampling fractions (coarse-to-fine with pose refinement)."""
    if options.resolution is not None:
        resolution, reasons["resolution"] = tuple(options.resolution), "asked for"
    else:
        (r0, r1), reasons["resolution"] = rules.resolution(need)
        if need.refine_poses:
            r0 = max(16, round(r1 / 4))
            reasons["resolution"] += "; pose refinement: start at a quarter of the final size (coarse-to-fine)"
        resolution = (r0, r1)
    if options.upsample_at is not None:
        upsample_at, reasons["upsample_at"] = tuple(options.upsample_at), "asked for"
    elif need.refine_poses:
        upsample_at = REFINE_UPSAMPLE_AT
        reasons["upsample_at"] = "pose refinement: later upsamplings, the cameras register to a coarse grid first"
    else:
        upsample_at = UPSAMPLE_AT
    return resolution, upsample_at


def _depth_loss(
    options: DensityOptions, scene: Scene, train_idx: tuple[int, ...], space: Space, reasons: dict[str, str]
) -> tuple[DepthRays | None, DensityOptions]:
    """The rays through the training photos' sparse points (or None) and `options` with the depth loss's weight:
    as given, else DEPTH_LOSS where the scene has sparse points and is contracted, else 0."""
    given, rel = options.depth_loss, scene.extra.get(SPARSE_KEY)
    rays, weight = None, 0.0
    if given == 0:
        reasons["depth_loss"] = "off (given)"
    elif rel is None or not space.sparse_depth:
        reasons["depth_loss"] = "left out: " + (
            f"no {SPARSE_KEY} in transforms.json (sparse points come from COLMAP through convert)"
            if rel is None
            else f"applies to contracted scenes only (this one: {space.name})"
        )
    elif (rays := sparse_depth_rays(scene, rel, train_idx)) is None:
        reasons["depth_loss"] = f"left out: {rel} has no points observed by the training photos"
    else:
        weight = given if given is not None else DEPTH_LOSS
        reasons["depth_loss"] = (
            f"{weight} on {rays.depth.numel()} sparse-point rays of {len(train_idx)} training photos"
        )
    if given and rays is None:
        raise UserError(f"depth_loss: {reasons['depth_loss'].removeprefix('left out: ')}")
    return rays, dataclasses.replace(options, depth_loss=weight)
