"""`train --method density` (the default): a TensoRF-style density field (VM planes and lines, `radiance.fields.fast`)
in its scene space, marched through an occupancy grid, coarse-to-fine.

Modules: `options` (its options group), `rules` (the grid, march and priors per kind of scene space), `defaults`
(resolving the options), `hooks` (upsampling, occupancy refresh and priors in the loop). Its runs are
`model.trained.Trained`: rays, density, colour, pose_opt.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Scene
from nerfpipe.model.checkpoint import restore_background, restore_space
from nerfpipe.model.field_model import EMPTY_OPACITY, MarchedModel, grid_step
from nerfpipe.model.methods.base import Method, Prepared, RunFiles, TrainContext
from nerfpipe.model.methods.density.defaults import resolve_options
from nerfpipe.model.methods.density.hooks import hooks_for
from nerfpipe.model.methods.density.options import DensityOptions, validate_options
from nerfpipe.model.spaces import make_space
from nerfpipe.model.trained import Trained, load_field_run
from nerfpipe.model.views import DepthRays
from nerfpipe.radiance.fields import TensoRF, make_field
from nerfpipe.radiance.fields.fast import (
    DEFAULT_ACTIVATION,
    DEFAULT_HIDDEN,
    TENSORF_RANK,
    has_stacked_factors,
    split_rank,
    unstack_adam_state,
)
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.space import Space

__all__ = ["DENSITY", "DensityMethod", "DensityOptions", "DensityPrepared", "density_model", "recorded_options"]

LR = 0.03
"""The grids' learning rate (the colour MLP's is LR / 20: `TensoRF.param_groups`)."""


@dataclass(frozen=True, kw_only=True)
class DensityPrepared(Prepared):
    options: DensityOptions
    space: Space
    depth_rays: DepthRays | None = None
    """Rays through the training photos' sparse points, where the depth loss is on."""


def density_model(options: DensityOptions, space: Space, device: torch.device, field_cfg: dict | None) -> MarchedModel:
    """The field in `space` (its box: the scene's aabb, NDC's box of the training cameras, or the contracted cube
    [-2, 2]^3), its occupancy grid and march step, from resolved `options`; `field_cfg` (a checkpoint's) rebuilds a
    saved field, None makes a new one. Background and appearance are set by the caller."""
    aabb = space.field_box
    if field_cfg is None:
        density_rank, app_rank = split_rank(options.rank)
        field_cfg = TensoRF(
            aabb=aabb,
            resolution=options.resolution[0],
            density_rank=density_rank,
            app_rank=app_rank,
            view_dependent=options.view_dependent,
            density_activation=options.density_activation,
            hidden=options.mlp_width,
        ).config()
    field = make_field(field_cfg).to(device)
    step = grid_step(aabb, options.resolution[1], options.step_ratio)  # in the grid's units
    # A cell is empty when one training step through it is nearly transparent (alpha < EMPTY_OPACITY): nerfacc's
    # rule (its threshold is on sigma x step). A bare density threshold kept cells long after the field had cleared
    # them.
    grid = OccupancyGrid(aabb, options.occupancy_resolution, threshold=EMPTY_OPACITY / step).to(device)
    return MarchedModel(
        field=field,
        space=space,
        grid=grid,
        step_size=step * space.step_unit(),
        render_step_factor=options.render_step_factor,
    )


def recorded_options(doc: dict[str, Any]) -> DensityOptions:
    """A run's resolved options from its config.json: `options`, or the `fast` group (and the top-level
    view_dependent) of runs written before methods, or the top level of runs written before that grouping."""
    stored = doc.get("options") if isinstance(doc.get("options"), dict) else doc.get("fast", doc)
    view_dependent = stored.get("view_dependent", doc.get("view_dependent"))
    return DensityOptions(
        resolution=(int(stored["resolution"][0]), int(stored["resolution"][1])),
        rank=tuple(int(r) for r in (stored.get("rank") or TENSORF_RANK)),
        step_ratio=float(stored["step_ratio"]),
        occupancy_resolution=int(stored["occupancy_resolution"]),
        render_step_factor=float(stored["render_step_factor"]),
        view_dependent=True if view_dependent is None else bool(view_dependent),
        density_activation=str(stored.get("density_activation", DEFAULT_ACTIVATION)),
        mlp_width=int(stored.get("mlp_width", DEFAULT_HIDDEN)),
    )


class DensityMethod(Method):
    name = "density"
    summary = "TensoRF-style density field, occupancy-grid marching, coarse-to-fine (the default)"
    Options = DensityOptions
    recorded_before = {"density_activation": DEFAULT_ACTIVATION, "mlp_width": DEFAULT_HIDDEN}

    def validate(self, options: DensityOptions) -> None:
        validate_options(options)

    def prepare(self, ctx: TrainContext, options: DensityOptions, reasons: dict[str, str]) -> DensityPrepared:
        reasons["scene_model"] = f"{ctx.space_kind.name}: {ctx.space_why}"
        space = make_space(ctx.space_kind, ctx.scene)
        if options.distortion > 0 and not space.distortion_loss:
            raise UserError(f"distortion applies to contracted scenes only (this one is {reasons['scene_model']})")
        resolved, rays = resolve_options(options, ctx, space, reasons)
        return DensityPrepared(options=resolved, space=space, depth_rays=rays)

    def default_lr(self) -> tuple[float, str]:
        return LR, f"{LR} for the density field's grids (its MLP at lr/20)"

    def build(self, ctx: TrainContext, prepared: DensityPrepared, state: dict | None) -> MarchedModel:
        if state is None:
            model = density_model(prepared.options, prepared.space, ctx.device, None)
            model.background = ctx.background
            return model
        space = restore_space(state, lambda kind: make_space(kind, ctx.scene))
        model = density_model(prepared.options, space, ctx.device, state["field_config"])
        model.background = restore_background(state, ctx.device)
        _load_weights(model, state)
        return model

    def hooks(self, ctx: TrainContext, prepared: DensityPrepared, model: MarchedModel) -> list:
        return hooks_for(prepared.options, model, prepared.depth_rays)

    def checkpoint(self, model: MarchedModel) -> dict[str, Any]:
        return {
            "field_config": model.field.config(),
            "field": model.field.state_dict(),
            "occupancy": model.grid.state_dict() if model.grid is not None else None,
            "space": model.space.to_dict(),
        }

    def optimizer_state(self, state: dict) -> dict:
        if has_stacked_factors(state["field"]):  # a run from before per-plane factors
            return unstack_adam_state(state["optimizer"])
        return state["optimizer"]

    def load(self, run: RunFiles, device: torch.device) -> Trained:
        return load_field_run(run, device, self.name, self._load_model)

    def _load_model(self, doc: dict, state: dict, scene: Scene, device: torch.device) -> MarchedModel:
        try:
            options = recorded_options(doc)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise UserError(f"config.json lacks a valid {exc} (written by another nerfpipe version?)") from None
        space = restore_space(state, lambda kind: make_space(kind, scene))
        model = density_model(options, space, device, state["field_config"])
        model.background = restore_background(state, device)
        _load_weights(model, state)
        return model


def _load_weights(model: MarchedModel, state: dict) -> None:
    model.field.load_state_dict(state["field"])
    if model.grid is not None and state["occupancy"] is not None:
        model.grid.load_state_dict(state["occupancy"])


DENSITY = DensityMethod()
