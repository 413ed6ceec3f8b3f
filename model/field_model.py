"""A field with what it needs to be rendered: its scene space, and (grid fields) its occupancy grid and march step.

`FieldModel.render(o, d, background, train=...)` takes world rays (scene frame, unit directions, t = Euclidean
distance; `radiance.camera`) and returns dict(rgb, depth, depth_median, acc, samples, ...) through the model-free
renderers of `radiance.render`, given callbacks over the field. Two kinds of model, one class each: `MarchedModel`
(a grid field, TensoRF, marched through the occupancy grid: `render_marched`; the density method) and
`HierarchicalModel` (the NeRF paper's MLPs, stratified + importance sampling: `render_rays_hierarchical`; the nerf
method). The scene space (`radiance.space`: box, NDC, contracted) maps the rays in and the depths out and gives the
march its steps; nothing here asks which space it is. Both are `model.methods.base.TrainModel`s.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nerfpipe.model.appearance import Appearance
from nerfpipe.model.background import Background
from nerfpipe.radiance.fields import Field, TensoRF, VanillaNeRF
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.regularizers import distortion_loss
from nerfpipe.radiance.render import (
    ColourRule,
    Marcher,
    RayColour,
    RgbFn,
    StratifiedSampler,
    render_marched,
    render_rays_hierarchical,
)
from nerfpipe.radiance.safe import eps
from nerfpipe.radiance.space import Space

__all__ = [
    "Inference",
    "EXACT",
    "FAST",
    "inference",
    "inference_record",
    "FieldModel",
    "MarchedModel",
    "HierarchicalModel",
    "EMPTY_OPACITY",
    "grid_step",
    "param_groups",
]

COLOR_THRESHOLD = 1e-4
"""Weight above which a sample's colour is evaluated (TensoRF's rule), in training and inference."""
INFER_COLOR_PER_RAY = None
"""Inference colours every sample above COLOR_THRESHOLD (`ColourRule.per_ray` None: no budget). The training
budget (16 samples a ray over the batch) bounds a step's cost while the field is a fog; at inference, where rays
stop early, it dropped the colour of the samples past it, and a ray that crosses more than 16 samples of weight
above the threshold came out darker (docs/MEASUREMENTS.md, "Rendering")."""
TRAIN_COLOR_MIN_PER_RAY = 1.0
"""Training also colours at least the batch's R largest weights (one a ray on average): at initialisation every
weight is ~1e-5, below the threshold, and no gradient would reach the density except through the background
term -- none at all on a black background. Threshold 0 (colour wherever the weight is not 0, up to 16 a ray) did
that too, at 3x the step time (docs/MEASUREMENTS.md, "Rendering")."""


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
FAST = Inference(min_transmittance=1e-2, color_keep=1e-2, step_scale=1.5)
"""What `render`, `eval` and `depth` use unless asked `--exact` (issue 54): rays stop below 1 % of the light,
colour only samples of weight >= 1 % (and each ray's largest, rescaled), at 1.5 x the inference step. Its speed and
PSNR against EXACT: docs/TRAINING.md "Inference" (`benchmarks/bench_infer.py`)."""


def inference(exact: bool) -> Inference:
    """The stages' choice (`render`, `eval`, `depth`): EXACT when asked `--exact`, else FAST."""
    return EXACT if exact else FAST


def inference_record(infer: Inference) -> dict:
    """The manifest's record of an Inference: its settings and its name (exact, fast, or custom)."""
    name = "exact" if infer == EXACT else "fast" if infer == FAST else "custom"
    return {"name": name, **dataclasses.asdict(infer)}


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
            rgb_fn=_rgb_fn(field, inference=True),
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


def _rgb_fn(field: TensoRF, inference: bool = False) -> RgbFn | RayColour | None:
    """The field's colour as the renderers' rgb_fn (None for a density-only field); inference: its no-grad fast path
    in two parts, the directions' term once per ray (`TensoRF.direction_codes`, `color_from_codes`: the same values
    up to float rounding)."""
    if not field.has_color:
        return None
    if inference and field.view_dependent:
        return RayColour(per_ray=field.direction_codes, colour=field.color_from_codes)
    if inference:
        return lambda x, d: field.color_from_codes(x, None)
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


def _copy_state(module: torch.nn.Module) -> dict[str, Any]:
    return copy.deepcopy(module.state_dict())


@dataclass(eq=False)
class FieldModel:
    """A field in its scene space with its background and appearance codes (module doc). Subclasses render."""

    field: Field
    space: Space
    background: Background | None = None
    appearance: Appearance | None = None  # per-image colour codes (train --appearance; model.appearance)

    chunk = 8192
    """Rays per evaluation chunk."""
    random_draws_per_ray = 1
    """Random numbers a training render draws per ray (data-parallel runs place them: `model.distributed`)."""

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
        each ray's training view (None: the evaluation rule, `model.appearance`). Not training, a grid field
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

    def _render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen, median, infer):
        raise NotImplementedError

    def param_groups(self, lr: float) -> list[dict]:
        """Adam's groups (`param_groups`)."""
        return param_groups(self.field.param_groups(lr), self.background, self.appearance, lr)

    def train_mode(self, on: bool) -> None:
        self.field.train(on)

    def after_step(self) -> None:
        self.field.touch()  # fused Adam leaves the version counters: the field's inference caches must know

    def learned(self) -> dict[str, torch.nn.Module]:
        """What the model learned, by name: the field, background and appearance codes (those it has)."""
        mods = {"field": self.field, "background": self.background, "appearance": self.appearance}
        return {k: v for k, v in mods.items() if v is not None}

    def snapshot(self) -> dict[str, Any]:
        """A copy of `learned`'s states and the field's grid resolution (None: a field without one)."""
        state = {k: _copy_state(v) for k, v in self.learned().items()}
        return state | {"resolution": getattr(self.field, "resolution", None)}

    def restore(self, snapshot: dict[str, Any]) -> bool:
        """Back to `snapshot`; when the field was upsampled since, the copy is resampled to today's resolution and
        True is returned (its parameters are new: the optimiser must start afresh)."""
        now = getattr(self.field, "resolution", None)
        resampled = now != snapshot["resolution"]
        if resampled:
            self.field.upsample(snapshot["resolution"])  # the copy's shapes, then its values
        for key, mod in self.learned().items():
            mod.load_state_dict(snapshot[key])
        if resampled:
            self.field.upsample(now)
        self.field.touch()
        return resampled

    def describe(self) -> dict[str, Any]:
        """The manifest's record of the model: the field's configuration, its view dependence, its space."""
        return {
            "field": self.field.config(),
            "view_dependent": self.field.view_dependent,
            "scene_model": self.space.name,
            "space": self.space.describe(),
        }


@dataclass(eq=False)
class MarchedModel(FieldModel):
    """A grid field (TensoRF) marched through its occupancy grid at `step_size` (training) and `step_size *
    render_step_factor` (inference), in march units (`Space.step_unit`)."""

    grid: OccupancyGrid | None = None  # over the space's field box
    step_size: float = 0.0
    render_step_factor: float = 1.0

    def _render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen, median, infer):
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

    def distortion(self, out: dict, o: Tensor, d: Tensor) -> Tensor:
        """mip-NeRF 360's distortion loss of a training render `out` of rays o, d [R, 3], in the space's normalised
        distance (`Space.normalized_distance`; contracted: the warped distance). Only where the space defines it:
        the fog it removes is what a short real capture grows near its cameras."""
        if not self.space.distortion_loss:
            raise ValueError(f"distortion: expected a space with a distortion loss, got {self.space.name}")
        idx = out["ray_indices"]
        s0 = self.space.normalized_distance(o, d, out["t_starts"], idx)
        s1 = self.space.normalized_distance(o, d, out["t_ends"], idx)
        return distortion_loss(out["weights"], s0, s1, idx, o.shape[0])

    def learned(self) -> dict[str, torch.nn.Module]:
        """The field, background, appearance codes and the occupancy grid."""
        return super().learned() | ({"grid": self.grid} if self.grid is not None else {})

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        if self.grid is not None:
            out["occupancy_skip_fraction"] = round(self.grid.skip_fraction, 4)
            out["march_step"] = {"train": self.step_size, "render": self.step_size * self.render_step_factor}
        return out


@dataclass(eq=False)
class HierarchicalModel(FieldModel):
    """The NeRF paper's coarse and fine MLPs: stratified samples in the space's box, importance samples, both nets."""

    chunk = 1024
    """256 samples x 256 activations per ray: smaller chunks."""

    @property
    def random_draws_per_ray(self) -> int:  # type: ignore[override]
        return self.field.n_coarse + self.field.n_fine

    def _render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen, median, infer):
        return _render_vanilla(self.field, o, d, space=self.space, background=background, jitter=train, generator=gen)


def grid_step(aabb: Tensor, resolution: int, ratio: float) -> float:
    """The march step: `ratio` voxels of a grid of `resolution` cells per axis over `aabb` [2, 3] (mean side)."""
    return float((aabb[1] - aabb[0]).mean()) / resolution * ratio


EMPTY_OPACITY = 0.003
"""Opacity of one training step below which an occupancy cell counts as empty (a higher one empties cells of
forward-facing scenes before their far wall is learned: docs/MEASUREMENTS.md, "Rendering")."""


def param_groups(
    field_groups: list[dict], background: Background | None, appearance: Appearance | None, lr: float
) -> list[dict]:
    """Adam's groups of a field model: its field's `field_groups`, a learned background colour's (at lr) and the
    appearance codes'."""
    groups = list(field_groups)
    extra = background.params() if background is not None else []
    if extra:
        groups.append({"params": extra, "lr": lr, "lr_scale": 1.0})
    if appearance is not None:
        groups += appearance.param_groups(lr)
    return groups
