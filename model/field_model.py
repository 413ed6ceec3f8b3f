"""A field with what it needs to be rendered: its scene space, occupancy grid and marching step.

`FieldModel.render(o, d, background, train=...)` takes world rays (scene frame, unit directions, t = Euclidean
distance; `radiance.camera`) and returns dict(rgb, depth, depth_median, acc, samples, ...) through the
model-free renderers of `radiance.render`, given callbacks over the field: `fast` fields march the occupancy
grid (`render_marched`), `vanilla` fields use the paper's stratified + importance sampling
(`render_rays_hierarchical`). The scene space (`radiance.space`: box, NDC, contracted) maps the rays in and the
depths out and gives the march its steps; nothing here asks which space it is.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Scene, is_forward_facing
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.background import Background
from nerfpipe.radiance.contraction import Contraction
from nerfpipe.radiance.fields import Field, TensoRF, VanillaNeRF, make_field
from nerfpipe.radiance.fields.fast import DEFAULT_ACTIVATION, DEFAULT_HIDDEN, TENSORF_RANK, split_rank
from nerfpipe.radiance.ndc import NDC, fit_ndc
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.regularizers import distortion_loss
from nerfpipe.radiance.render import ColourRule, Marcher, StratifiedSampler, render_marched, render_rays_hierarchical
from nerfpipe.radiance.safe import eps
from nerfpipe.radiance.space import FAR, SPACES, Box, Contracted, NDCSpace, Space

__all__ = ["ModelSettings", "Inference", "FieldModel", "build_model", "make_space", "choose_space", "scene_ndc"]

COLOR_THRESHOLD = 1e-4
"""Weight above which a sample's colour is evaluated (TensoRF's rule), in training and inference."""
INFER_COLOR_PER_RAY = None
"""Inference colours every sample above COLOR_THRESHOLD (`ColourRule.per_ray` None: no budget). The training
budget (16 samples a ray over the batch) bounds a step's cost while the field is a fog; at inference, where rays
stop early, it dropped the colour of the samples past it, and a ray that crosses more than 16 samples of weight
above the threshold came out darker: the fern (relu density, 5,100 steps) at render_step_factor 0.25 scored 23.39
dB with it and 24.84 without (0.5: 24.81 and 24.82; 2026-11-28)."""
TRAIN_COLOR_MIN_PER_RAY = 1.0
"""Training also colours at least the batch's R largest weights (one a ray on average): at initialisation every
weight is ~1e-5, below the threshold, and no gradient would reach the density except through the background
term -- none at all on a black background (tiny-NeRF's npz trained to 12.3 dB and stayed). Threshold 0 (colour
wherever the weight is not 0, up to 16 a ray) did that too, at 3x the step time: tiny npz, 120 s, 2 idle cores,
889 steps, 30.05 dB."""


@dataclass(frozen=True, kw_only=True)
class ModelSettings:
    """What a field model is built from: the subset of train's Config that rendering needs (config.json)."""

    field: str
    """"fast" or "vanilla"."""
    resolution: tuple[int, int]
    """fast: grid resolution at the start and at the end of training."""
    rank: tuple[int, ...] = TENSORF_RANK
    """fast: the VM field's density and appearance components per plane, 2 counts or 6 (per plane:
    `radiance.fields.fast.split_rank`; a new field's, a saved one keeps its own). Runs from before the option were
    all TENSORF_RANK."""
    step_ratio: float
    """fast: marching step in voxels of the final grid."""
    occupancy_resolution: int
    """fast: occupancy grid cells per axis."""
    render_step_factor: float
    """fast: inference marches at this fraction of the training step."""
    view_dependent: bool | None
    """Colour depends on view direction (None: on)."""
    density_activation: str = DEFAULT_ACTIVATION
    """fast: a new field's density activation (`radiance.fields.fast.TensoRF`, with that activation's shift); a saved
    field keeps its own. Runs from before the option were all softplus."""
    mlp_width: int = DEFAULT_HIDDEN
    """fast: a new field's colour MLP width (`TensoRF(hidden=...)`); a saved field keeps its own. Runs from before the
    option were all DEFAULT_HIDDEN."""

    @classmethod
    def from_config(cls, doc: dict[str, Any], where: str) -> ModelSettings:
        """From a run's config.json (train's resolved Config: the fast field's options under "fast"; runs from
        before that grouping hold them at the top level); UserError naming a missing key."""
        try:
            fast = doc["fast"] if "fast" in doc else doc
            rank = fast.get("rank") or TENSORF_RANK
            return cls(
                field=str(doc["field"]),
                resolution=(int(fast["resolution"][0]), int(fast["resolution"][1])),
                rank=tuple(int(r) for r in rank),
                step_ratio=float(fast["step_ratio"]),
                occupancy_resolution=int(fast["occupancy_resolution"]),
                render_step_factor=float(fast["render_step_factor"]),
                view_dependent=doc.get("view_dependent"),
                density_activation=str(fast.get("density_activation", DEFAULT_ACTIVATION)),
                mlp_width=int(fast.get("mlp_width", DEFAULT_HIDDEN)),
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise UserError(
                f"{where}: config.json lacks a valid {exc} (written by another nerfpipe version?)"
            ) from None


@dataclass(frozen=True, kw_only=True)
class Inference:
    """How a `fast` field renders when not training (vanilla fields ignore it): early ray termination and step."""

    min_transmittance: float | None = None
    """A ray stops once less light than this gets through (acc, rgb off by at most this); None: the rays' dtype
    epsilon (float32: 1.2e-7, below the rounding of any value in [0, 1]: what render, depth and eval use)."""
    step_scale: float = 1.0
    """March at this multiple of the run's inference step (the viewer's coarse preview: 2)."""
    color_keep: float | None = None
    """Colour only the samples whose weight is at least this and each ray's largest, each ray's colour rescaled
    to its full weight (the viewer's coarse preview); None: every sample above COLOR_THRESHOLD (what render,
    depth and eval use)."""


EXACT = Inference()
"""Inference's default: rays stop once less than the dtype's epsilon of the light gets through."""


def _render_fast(
    field: TensoRF,
    marcher: Marcher,
    rays_o: Tensor,  # [R, 3] march rays (`Space.to_march`)
    rays_d: Tensor,  # [R, 3] unit
    *,
    background: Tensor,  # [3] or [R, 3]
    jitter: bool = False,
    with_median: bool = False,
    infer: Inference | None = None,
) -> dict[str, Tensor]:
    """TensoRF + occupancy grid in the marcher's space: radiance.render.render_marched over the field's density
    and colour (training, and infer=None), early-terminating otherwise."""
    if infer is not None:
        marcher = dataclasses.replace(marcher, step_size=marcher.step_size * infer.step_scale)
        out = render_marched(
            rays_o,
            rays_d,
            marcher=marcher,
            sigma_fn=field.density_inference,
            rgb_fn=_rgb_fn(field),
            background=background,
            with_median=with_median,
            min_transmittance=_min_transmittance(infer, rays_o),
            colour=ColourRule(threshold=COLOR_THRESHOLD, per_ray=INFER_COLOR_PER_RAY, keep=infer.color_keep),
        )
        return {**out, "samples": torch.tensor(float(out["samples"]))}
    if jitter:  # training
        colour = ColourRule(threshold=COLOR_THRESHOLD, min_per_ray=TRAIN_COLOR_MIN_PER_RAY)
    else:  # the differentiable march at the inference step (test-time optimisation): inference's colour rule
        colour = ColourRule(threshold=COLOR_THRESHOLD, per_ray=INFER_COLOR_PER_RAY)
    out = render_marched(
        rays_o,
        rays_d,
        marcher=marcher,
        sigma_fn=field.density,
        rgb_fn=_rgb_fn(field),
        background=background,
        jitter=jitter,
        with_median=with_median,
        colour=colour,
    )
    return {**out, "samples": torch.tensor(float(out["ray_indices"].numel()))}


def _min_transmittance(infer: Inference, rays_o: Tensor) -> float:
    return eps(rays_o.dtype) if infer.min_transmittance is None else infer.min_transmittance


def _rgb_fn(field: TensoRF):
    """The field's colour as the renderers' rgb_fn (None for a density-only field)."""
    if not field.has_color:
        return None
    return lambda x, d: field.color(x, d if field.view_dependent else None)


def _rgb_sigma(net, view_dependent: bool):
    """A NeRF MLP (x, d) -> (sigma, rgb | None) as render_rays' rgb_sigma_fn (rgb 0 for density-only)."""

    def fn(x: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        sigma, rgb = net(x, d if view_dependent else None)
        if rgb is None:
            rgb = torch.zeros(*sigma.shape, 3, dtype=sigma.dtype, device=sigma.device)
        return rgb, sigma

    return fn


def _render_vanilla(
    field: VanillaNeRF,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    space: Space,
    background: Tensor,  # [3] or [R, 3]
    jitter: bool,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """NeRF: n_coarse stratified samples in the space's box, n_fine importance samples, the fine net on all of
    them (radiance.render.render_rays_hierarchical)."""
    t_near, t_far = space.box_segment(rays_o, rays_d)
    out = render_rays_hierarchical(
        rays_o,
        rays_d,
        near=t_near,
        far=t_far,
        n_fine=field.n_fine,
        background=background,
        coarse_sampler=StratifiedSampler(n_samples=field.n_coarse, jitter=jitter, generator=generator),
        coarse_fn=_rgb_sigma(field.coarse, field.view_dependent),
        fine_fn=_rgb_sigma(field.fine, field.view_dependent),
    )
    out["rgb_coarse"] = out["coarse"]["rgb"]
    out["samples"] = torch.tensor(float(out["coarse"]["t_starts"].numel() + out["t_starts"].numel()))
    return out


@dataclass
class FieldModel:
    field: Field
    grid: OccupancyGrid | None  # over the space's field box (fast fields)
    kind: str  # the field's kind: fast | vanilla
    space: Space
    step_size: float  # training march step, march units (inference: step_size * render_step_factor)
    render_step_factor: float = 1.0
    background: Background | None = None
    appearance: Appearance | None = None  # per-image colour codes (train --appearance; model.appearance)

    @property
    def chunk(self) -> int:
        """Rays per evaluation chunk (vanilla: 256 samples x 256 activations per ray)."""
        return 8192 if self.kind == "fast" else 1024

    def render(
        self,
        o: Tensor,
        d: Tensor,
        background: Tensor,
        *,
        train: bool,
        gen=None,
        median=False,
        view=None,
        infer: Inference | None = Inference(),
    ):
        """World rays o, d [R, 3] (unit d) -> dict(rgb, depth, depth_median, acc, ...); depths are distances
        along the world rays whatever space the field lives in. With per-image appearance, `view` [R] gives
        each ray's training view (None: the evaluation rule, `model.appearance`). Not training, a fast field
        stops each ray early (`infer`; the outputs are then per ray only, plus `samples`, and carry no gradient);
        infer=None renders with the plain, differentiable marcher at the inference step (test-time optimisation)."""
        out = self._render_world(o, d, background, train=train, gen=gen, median=median, infer=infer)
        if self.appearance is not None:
            for key in ("rgb", "rgb_coarse"):
                if key in out:
                    acc = out["acc"] if key == "rgb" else out["coarse"]["acc"]
                    out[key] = self.appearance(out[key], acc, background, view)
        return out

    def _render_world(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen, median, infer):
        o_m, d_m, valid = self.space.to_march(o, d)
        out = self._render(o_m, d_m, background, train=train, gen=gen, median=median, infer=infer)
        if valid is None:
            return out
        for key in ("depth", "depth_median"):
            if key in out:
                out[key] = self.space.depth_from_march(o, d, o_m, d_m, out[key])
        if not bool(valid.all()):  # rays the space cannot map (NDC: away from the reference view) see nothing
            out["depth"] = torch.where(valid, out["depth"], torch.zeros_like(out["depth"]))
        return out

    def distortion(self, out: dict, o: Tensor, d: Tensor) -> Tensor:
        """mip-NeRF 360's distortion loss of a training render `out` of rays o, d [R, 3], in the space's normalised
        distance (`Space.normalized_distance`; contracted: the warped distance). Only where the space defines it:
        the fog it removes is what a short real capture grows near its cameras."""
        if self.kind != "fast" or not self.space.distortion_loss:
            raise ValueError(
                f"distortion: expected a fast field in a space with a distortion loss, got {self.kind} "
                f"in {self.space.name}"
            )
        idx = out["ray_indices"]
        s0 = self.space.normalized_distance(o, d, out["t_starts"], idx)
        s1 = self.space.normalized_distance(o, d, out["t_ends"], idx)
        return distortion_loss(out["weights"], s0, s1, idx, o.shape[0])

    def _render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen, median, infer):
        if self.kind == "fast":
            step = self.step_size if train else self.step_size * self.render_step_factor
            return _render_fast(
                self.field,
                Marcher(space=self.space, grid=self.grid, step_size=step),
                o,
                d,
                background=background,
                jitter=train,
                with_median=median,
                infer=None if train else infer,
            )
        return _render_vanilla(self.field, o, d, space=self.space, background=background, jitter=train, generator=gen)


EMPTY_OPACITY = 0.003
"""Opacity of one training step below which an occupancy cell counts as empty. tiny npz, 120 s (loaded machine):
0.01 -> 30.81 dB, 0.003 -> 30.98 dB; the NDC test scene: 0.01 empties cells before the far wall is learned (22.5 dB,
depth off by 50 %), 0.003 -> 24.4 dB, 7.9 %."""


def choose_space(scene_model: str, scene: Scene, *, plain_background: bool) -> tuple[type[Space], str]:
    """(the space's class, why) for `train --scene-model`. "auto": NDC when the cameras are forward-facing (all
    within 45 degrees of their mean direction); the box when the photos have alpha or a plain background colour
    (nothing to model outside the object's box); contracted otherwise (real photos see a background beyond the
    box)."""
    if scene_model != "auto":
        if scene_model not in SPACES:
            raise UserError(f"unknown scene model {scene_model!r}: expected auto, {', '.join(SPACES)}")
        return SPACES[scene_model], f"asked for (scene_model={scene_model})"
    if is_forward_facing(scene):
        return NDCSpace, "forward-facing cameras (all within 45 degrees of their mean direction)"
    if plain_background:
        return Box, "images with alpha or a plain background colour: nothing to model outside the box"
    return Contracted, "opaque photos whose background is not a plain colour: space beyond the box is contracted"


def scene_ndc(scene: Scene) -> NDC:
    """NDC of the scene's mean camera; its near plane is the scene's near bound."""
    if not (scene.near > 0 and math.isfinite(scene.near)):
        raise UserError(f"{scene.root}: NDC needs a near bound > 0 in transforms.json, got near={scene.near}")
    return fit_ndc(np.stack([f.world_from_cam for f in scene.frames]), scene.frame_intrinsics(0), scene.near)


def _box(rows) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    lo, hi = np.asarray(rows, dtype=np.float64).reshape(2, 3).tolist()
    return tuple(lo), tuple(hi)  # type: ignore[return-value]


def make_space(kind: type[Space], scene: Scene) -> Space:
    """The space of class `kind` for `scene`: its box and near/far bounds (Box), the NDC of its mean camera and
    the box of every training camera's frustum (NDCSpace), the contraction around its box (Contracted)."""
    if kind is NDCSpace:
        ndc = scene_ndc(scene)
        poses = np.stack([f.world_from_cam for f in scene.frames])
        intr = [scene.frame_intrinsics(i) for i in range(len(scene.frames))]
        return NDCSpace(ndc=ndc, box=_box(ndc.box(poses, intr)))
    if kind is Contracted:
        return Contracted(contraction=Contraction(scene.aabb), near=float(scene.near))
    return Box(aabb=_box(scene.aabb), near=float(scene.near), far=float(scene.far if math.isfinite(scene.far) else FAR))


def build_model(
    settings: ModelSettings,
    space: Space,
    device: torch.device,
    field_cfg: dict | None,
    background: Background | None = None,
) -> FieldModel:
    """The field in `space` (its box: the scene's aabb, NDC's box of the training cameras, or the contracted
    cube [-2, 2]^3), its occupancy grid (fast) and render settings. `field_cfg` (a checkpoint's) rebuilds a
    saved field; None makes a new one from `settings`."""
    if not space.straight_rays and settings.field != "fast":
        raise UserError(f"scene_model {space.name} needs the fast field (vanilla samples straight rays in a box)")
    aabb = space.field_box
    view_dep = True if settings.view_dependent is None else settings.view_dependent
    if field_cfg is None:
        if settings.field == "fast":
            density_rank, app_rank = split_rank(settings.rank)
            field_cfg = TensoRF(
                aabb=aabb,
                resolution=settings.resolution[0],
                density_rank=density_rank,
                app_rank=app_rank,
                view_dependent=view_dep,
                density_activation=settings.density_activation,
                hidden=settings.mlp_width,
            ).config()
        else:
            field_cfg = VanillaNeRF(view_dependent=view_dep).config()
    field = make_field(field_cfg).to(device)
    step = _step_size(aabb, settings.resolution[1], settings.step_ratio)  # in the grid's units
    grid = None
    if field_cfg["kind"] == "fast":
        # A cell is empty when one training step through it is nearly transparent (alpha < EMPTY_OPACITY): nerfacc's
        # rule (its threshold is on sigma x step). A bare density threshold of 0.01 kept cells for ~1400 steps
        # after the field had cleared them (tiny npz: 60 % of samples in "occupied" free space, 26.2 dB at 40 s).
        grid = OccupancyGrid(aabb, settings.occupancy_resolution, threshold=EMPTY_OPACITY / step).to(device)
    background = background if background is not None else Background("fixed")
    return FieldModel(
        field,
        grid,
        field_cfg["kind"],
        space,
        step * space.step_unit(),
        settings.render_step_factor,
        background.to(device),
    )


def _step_size(aabb: Tensor, resolution: int, ratio: float) -> float:
    return float((aabb[1] - aabb[0]).mean()) / resolution * ratio
