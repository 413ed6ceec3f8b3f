"""`train --method nerf`: the NeRF paper's model (Mildenhall et al. 2020): coarse and fine MLPs with positional
encoding, 64 stratified and 128 importance samples a ray in the scene's box (`radiance.fields.vanilla`).

It samples straight rays in a box, so it keeps the box space whatever the scene model's rule chose (the reason
says so). Its runs are `model.trained.Trained`: rays, density, colour, pose_opt.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from nerfpipe.data.transforms import Scene
from nerfpipe.model.checkpoint import restore_background, restore_space
from nerfpipe.model.field_model import HierarchicalModel
from nerfpipe.model.methods.base import Method, Prepared, RunFiles, TrainContext
from nerfpipe.model.spaces import make_space
from nerfpipe.model.trained import Trained, load_field_run
from nerfpipe.radiance.fields import VanillaNeRF, make_field
from nerfpipe.radiance.space import Box

__all__ = ["NERF", "NerfMethod", "NerfOptions"]

LR = 5e-4


@dataclass(frozen=True, kw_only=True)
class NerfOptions:
    """The NeRF paper's model."""

    view_dependent: bool | None = None
    """Colour depends on view direction (None: on for every scene; off suits Lambertian scenes)."""


class NerfMethod(Method):
    name = "nerf"
    summary = "the NeRF paper's MLPs: stratified + importance samples in the scene's box"
    Options = NerfOptions

    def prepare(self, ctx: TrainContext, options: NerfOptions, reasons: dict[str, str]) -> Prepared:
        kind, why = ctx.space_kind, ctx.space_why
        if not kind.straight_rays:
            kind, why = Box, f"the nerf method samples straight rays in a box (no {kind.name} space)"
        reasons["scene_model"] = f"{kind.name}: {why}"
        view_dependent = True if options.view_dependent is None else options.view_dependent
        return Prepared(options=NerfOptions(view_dependent=view_dependent), space=make_space(kind, ctx.scene))

    def default_lr(self) -> tuple[float, str]:
        return LR, f"{LR:g} for the NeRF MLPs"

    def build(self, ctx: TrainContext, prepared: Prepared, state: dict | None) -> HierarchicalModel:
        if state is None:
            # made from its config, as every field is restored (the first instance's draws keep runs as they were)
            field = make_field(VanillaNeRF(view_dependent=prepared.options.view_dependent).config()).to(ctx.device)
            return HierarchicalModel(field=field, space=prepared.space, background=ctx.background)
        return self._restore(state, ctx.scene, ctx.device)

    def checkpoint(self, model: HierarchicalModel) -> dict[str, Any]:
        return {
            "field_config": model.field.config(),
            "field": model.field.state_dict(),
            "occupancy": None,
            "space": model.space.to_dict(),
        }

    def load(self, run: RunFiles, device: torch.device) -> Trained:
        return load_field_run(run, device, self.name, lambda doc, state, scene, dev: self._restore(state, scene, dev))

    def _restore(self, state: dict, scene: Scene, device: torch.device) -> HierarchicalModel:
        space = restore_space(state, lambda kind: make_space(kind, scene))
        field = make_field(state["field_config"]).to(device)
        field.load_state_dict(state["field"])
        return HierarchicalModel(field=field, space=space, background=restore_background(state, device))


NERF = NerfMethod()
