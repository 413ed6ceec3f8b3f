"""`train --method sdf`: a signed distance (the ellipsoid inscribed in the box plus a learned VM grid), turned into
opacity by NeuS's logistic ratio with a learned sharpness, an Eikonal term by finite differences one grid cell wide,
a colour network that sees the normal, coarse-to-fine growth. Its runs can render rays, give a signed distance
(`mesh` extracts the zero level set: no threshold) and a colour at points.

Objects in their box (photos with alpha, masks or a plain background), and real captures (a contracted scene: the
signed distance in the scene's box, a density field in contracted space for what lies outside it, as neus-facto and
BakedSDF split them); a forward-facing (NDC) scene is refused in one line. Modules: `options` (the options group),
`neus` (the opacity and compositing maths), `field` (the signed distance and colour), `outside` (the density field
beyond the box), `model` (the `TrainModel`), `hooks` (Eikonal term, growth, the outside field's smoothing), `run`
(the run for the stages and the self-check).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch

from nerfpipe.data.checks import Check
from nerfpipe.data.errors import UserError
from nerfpipe.model.checkpoint import read_checkpoint, restore_appearance, restore_background, restore_space
from nerfpipe.model.methods.base import Method, Prepared, RunFiles, TrainContext
from nerfpipe.model.methods.sdf.field import SdfField
from nerfpipe.model.methods.sdf.hooks import hooks_for
from nerfpipe.model.methods.sdf.model import SdfModel
from nerfpipe.model.methods.sdf.options import (
    CURVATURE_REAL,
    DENSE_GRID,
    REFINE,
    RESOLUTION,
    SAMPLES,
    UPSAMPLE_AT,
    SdfOptions,
    validate_options,
)
from nerfpipe.model.methods.sdf.outside import Outside
from nerfpipe.model.methods.sdf.run import SdfRun, sdf_checks
from nerfpipe.model.spaces import make_space
from nerfpipe.model.trained import read_run_scene
from nerfpipe.radiance.space import Box, Contracted, Space

__all__ = ["SDF", "SdfMethod", "SdfOptions"]

LR = 0.02
"""The grids' learning rate (the colour network's lr / 20, the sharpness's lr / 3: `SdfField.param_groups`)."""


@dataclass(frozen=True, kw_only=True)
class SdfPrepared(Prepared):
    options: SdfOptions
    space: Space


def sdf_box(space: Space) -> torch.Tensor:
    """[2, 3] the box the signed distance lives in: the field's box of an object scene, the inner (uncontracted)
    box of a contracted one."""
    return space.contraction.inner_aabb if isinstance(space, Contracted) else space.field_box


def _model(
    options: SdfOptions, space: Space, field_cfg: dict | None, device: torch.device, outside: Outside | None = None
) -> SdfModel:
    """The model of resolved `options` in `space`: a fresh field (`field_cfg` None) or one of `field_cfg` (its state
    loaded by the caller); `outside` as given, else a fresh one in a contracted space."""
    if field_cfg is None:
        field_cfg = SdfField(
            aabb=sdf_box(space),
            resolution=options.resolution[0],
            view_dependent=options.view_dependent,
            radius=options.init_radius,
            dense=options.dense_grid,
        ).config()
    field = SdfField(**field_cfg).to(device)
    if outside is None and isinstance(space, Contracted):
        outside = Outside.create(space.contraction).to(device)
    return SdfModel(
        field=field,
        space=space,
        samples=options.sdf_samples,
        refine=options.sdf_refine,
        outside=outside,
        curvature=options.curvature > 0,
    )


class SdfMethod(Method):
    name = "sdf"
    summary = (
        "signed distance (an ellipsoid start + a coarse dense grid + VM grid), NeuS opacity, Eikonal term: objects in "
        "their box, real captures with a density field outside the box"
    )
    Options = SdfOptions

    def validate(self, options: SdfOptions) -> None:
        validate_options(options)

    def prepare(self, ctx: TrainContext, options: SdfOptions, reasons: dict[str, str]) -> SdfPrepared:
        if ctx.space_kind not in (Box, Contracted):
            raise UserError(
                f"the sdf method models objects in their box or real captures around one (contracted); this scene "
                f"is {ctx.space_kind.name} ({ctx.space_why}): use method=density, or scene_model=box or contract"
            )
        if ctx.refine_poses:
            raise UserError("the sdf method does not refine poses (refine_poses): use method=density")
        box = ctx.space_kind is Box
        if box:
            reasons["scene_model"] = f"box: {ctx.space_why}"
            reasons["outside"] = "left out: an object scene, nothing to model beyond the box"
        else:
            reasons["scene_model"] = (
                f"contract: {ctx.space_why}; the signed distance in the scene's box, a density field outside it"
            )
        resolved = replace(
            options,
            resolution=options.resolution or RESOLUTION,
            upsample_at=options.upsample_at if options.upsample_at is not None else UPSAMPLE_AT,
            sdf_samples=options.sdf_samples or SAMPLES,
            sdf_refine=options.sdf_refine or REFINE,
            view_dependent=True if options.view_dependent is None else options.view_dependent,
            curvature=options.curvature if options.curvature is not None else (0.0 if box else CURVATURE_REAL),
            dense_grid=options.dense_grid if options.dense_grid is not None else (DENSE_GRID if box else 0),
        )
        curvature_why = (
            "0 (off) for objects in their box: it rounds off their edges (docs/SDF.md)"
            if box
            else f"{CURVATURE_REAL:g} for real captures: the surface comes out rippled without it (docs/SDF.md)"
        )
        dense_why = (
            f"{DENSE_GRID} per axis under the planes and lines for objects in their box: the coarse shape (docs/SDF.md)"
            if box
            else "0 (none) for real captures: on the fox it filled the unseen back of the box (docs/SDF.md)"
        )
        for name, why in (
            ("resolution", "32 to 128 (coarse-to-fine)"),
            ("upsample_at", "at 10, 20, 30, 40 % of the run"),
            ("sdf_samples", f"{SAMPLES} intervals a ray in the box"),
            ("sdf_refine", f"{REFINE} sub-intervals an interval near the surface"),
            ("view_dependent", "on for every scene"),
            ("curvature", curvature_why),
            ("dense_grid", dense_why),
        ):
            reasons[name] = "asked for" if getattr(options, name) is not None else why
        return SdfPrepared(options=resolved, space=make_space(ctx.space_kind, ctx.scene))

    def default_lr(self) -> tuple[float, str]:
        return LR, f"{LR} for the signed distance's grids (its colour network at lr/20)"

    def build(self, ctx: TrainContext, prepared: SdfPrepared, state: dict | None) -> SdfModel:
        if state is None:
            model = _model(prepared.options, prepared.space, None, ctx.device)
            model.background = ctx.background
            return model
        space = restore_space(state, lambda kind: make_space(kind, ctx.scene))
        outside = _outside(state, space, ctx.device)
        model = _model(prepared.options, space, state["sdf_field_config"], ctx.device, outside)
        model.field.load_state_dict(state["sdf_field"])
        model.background = restore_background(state, ctx.device)
        return model

    def hooks(self, ctx: TrainContext, prepared: SdfPrepared, model: SdfModel) -> list:
        return hooks_for(prepared.options, outside=model.outside is not None)

    def checkpoint(self, model: SdfModel) -> dict[str, Any]:
        state = {
            "sdf_field_config": model.field.config(),
            "sdf_field": model.field.state_dict(),
            "sdf_samples": model.samples,
            "sdf_refine": model.refine,
            "space": model.space.to_dict(),
        }
        if model.outside is not None:
            state |= {"sdf_outside_config": model.outside.config(), "sdf_outside": model.outside.field.state_dict()}
        return state

    def checks(self, model: SdfModel) -> list[Check]:
        return sdf_checks(model)

    def load(self, run: RunFiles, device: torch.device) -> SdfRun:
        state = read_checkpoint(run.checkpoint, device)
        scene = read_run_scene(run.run_dir, run.config)
        try:
            space = restore_space(state, lambda kind: make_space(kind, scene))
            field = SdfField(**state["sdf_field_config"]).to(device)
            field.load_state_dict(state["sdf_field"])
            samples = int(state["sdf_samples"])
            refine = int(state.get("sdf_refine", 1))
            outside = _outside(state, space, device)
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise UserError(f"{run.checkpoint}: not an sdf checkpoint this version reads ({exc})") from None
        model = SdfModel(
            field=field,
            space=space,
            samples=samples,
            refine=refine,
            background=restore_background(state, device),
            outside=outside,
        )
        model.appearance = restore_appearance(state, device)
        model.train_mode(False)
        return SdfRun(
            scene=scene,
            model=model,
            device=device,
            background=model.background.eval_colour().detach(),
            downscale=run.downscale,
        )


def _outside(state: dict, space: Space, device: torch.device) -> Outside | None:
    """The outside field a checkpoint holds (a contracted scene's), or None (an object scene's)."""
    if not isinstance(space, Contracted):
        return None
    outside = Outside.from_config(state["sdf_outside_config"], space.contraction).to(device)
    outside.field.load_state_dict(state["sdf_outside"])
    return outside


SDF = SdfMethod()
