"""A field with what it needs to be rendered: occupancy grid, box, near/far, marching step, NDC wrapping.

`FieldModel.render(o, d, background, train=...)` takes world rays (scene frame, unit directions, t = Euclidean
distance; `radiance.camera`) and returns dict(rgb, depth, depth_median, acc, samples, ...) through the
model-free renderers of `radiance.render`, given callbacks over the field: `fast` fields march the occupancy
grid (`render_marched`), `vanilla` fields use the paper's stratified + importance sampling
(`render_rays_hierarchical`). With an NDC map (forward-facing captures) the field lives in NDC of the mean
camera and depths come back as distances along the world rays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from data.errors import UserError
from data.transforms import Scene, is_forward_facing
from model.appearance import Appearance
from model.background import Background
from radiance.aabb import ray_aabb_segment
from radiance.contraction import CONTRACTED_BOX, Contraction, normalized_distance
from radiance.fields import Field, TensoRF, VanillaNeRF, make_field
from radiance.ndc import NDC, fit_ndc
from radiance.occupancy import OccupancyGrid
from radiance.regularizers import distortion_loss
from radiance.render import (
    StratifiedSampler,
    render_contracted,
    render_contracted_terminating,
    render_marched,
    render_marched_terminating,
    render_rays_hierarchical,
)
from radiance.safe import eps

__all__ = ["ModelSettings", "Inference", "FieldModel", "build_model", "scene_ndc", "choose_scene_model"]

COLOR_THRESHOLD = 1e-4
"""Weight above which a sample's colour is evaluated (TensoRF's rule), in training and inference."""
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
    step_ratio: float
    """fast: marching step in voxels of the final grid."""
    occupancy_resolution: int
    """fast: occupancy grid cells per axis."""
    render_step_factor: float
    """fast: inference marches at this fraction of the training step."""
    view_dependent: bool | None
    """Colour depends on view direction (None: on)."""

    @classmethod
    def from_config(cls, doc: dict[str, Any], where: str) -> ModelSettings:
        """From a run's config.json (train's resolved Config); UserError naming a missing key."""
        try:
            return cls(field=str(doc["field"]), resolution=(int(doc["resolution"][0]), int(doc["resolution"][1])),
                       step_ratio=float(doc["step_ratio"]), occupancy_resolution=int(doc["occupancy_resolution"]),
                       render_step_factor=float(doc["render_step_factor"]),
                       view_dependent=doc.get("view_dependent"))  # fmt: skip
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


def _render_fast(
    field: TensoRF,
    grid: OccupancyGrid,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    near: float,
    far: float,
    step_size: float,
    background: Tensor,  # [3] or [R, 3]
    jitter: bool = False,
    with_median: bool = False,
    infer: Inference | None = None,
) -> dict[str, Tensor]:
    """TensoRF + occupancy grid: radiance.render.render_marched over the field's density and colour (training),
    its early-terminating twin otherwise."""
    if infer is not None:
        out = render_marched_terminating(
            rays_o, rays_d, grid=grid, sigma_fn=field.density_inference, rgb_fn=_rgb_fn(field), near=near, far=far,
            step_size=step_size * infer.step_scale, background=background, with_median=with_median,
            min_transmittance=_min_transmittance(infer, rays_o), **_colour_rule(infer),
        )  # fmt: skip
        return {**out, "samples": torch.tensor(float(out["samples"]))}
    out = render_marched(
        rays_o, rays_d, grid=grid, sigma_fn=field.density, rgb_fn=_rgb_fn(field), near=near, far=far,
        step_size=step_size, background=background, jitter=jitter, with_median=with_median,
        color_threshold=COLOR_THRESHOLD, color_min_per_ray=TRAIN_COLOR_MIN_PER_RAY if jitter else 0.0,
    )  # fmt: skip
    return {**out, "samples": torch.tensor(float(out["ray_indices"].numel()))}


def _colour_rule(infer: Inference) -> dict:
    return {"color_threshold": COLOR_THRESHOLD, "color_keep": infer.color_keep}


def _min_transmittance(infer: Inference, rays_o: Tensor) -> float:
    return eps(rays_o.dtype) if infer.min_transmittance is None else infer.min_transmittance


def _rgb_fn(field: TensoRF):
    """The field's colour as the renderers' rgb_fn (None for a density-only field)."""
    if not field.has_color:
        return None
    return lambda x, d: field.color(x, d if field.view_dependent else None)


def _render_fast_contracted(
    field: TensoRF,
    grid: OccupancyGrid,
    contraction: Contraction,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    near: float,
    step_size: float,  # world units inside the inner box
    background: Tensor,
    jitter: bool = False,
    with_median: bool = False,
    infer: Inference | None = None,
) -> dict[str, Tensor]:
    """TensoRF in contracted space (unbounded scenes): radiance.render.render_contracted (training), its
    early-terminating twin otherwise."""
    if infer is not None:
        out = render_contracted_terminating(
            rays_o, rays_d, grid=grid, contraction=contraction, sigma_fn=field.density_inference, rgb_fn=_rgb_fn(field),
            near=near, step_size=step_size * infer.step_scale, background=background, with_median=with_median,
            min_transmittance=_min_transmittance(infer, rays_o), **_colour_rule(infer),
        )  # fmt: skip
        return {**out, "samples": torch.tensor(float(out["samples"]))}
    out = render_contracted(
        rays_o, rays_d, grid=grid, contraction=contraction, sigma_fn=field.density, rgb_fn=_rgb_fn(field),
        near=near, step_size=step_size, background=background, jitter=jitter, with_median=with_median,
        color_threshold=COLOR_THRESHOLD, color_min_per_ray=TRAIN_COLOR_MIN_PER_RAY if jitter else 0.0,
    )  # fmt: skip
    return {**out, "samples": torch.tensor(float(out["ray_indices"].numel()))}


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
    aabb: Tensor,  # [2, 3]
    near: float,
    far: float,
    background: Tensor,  # [3] or [R, 3]
    jitter: bool,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """NeRF: n_coarse stratified samples in the box, n_fine importance samples, the fine net on all of them
    (radiance.render.render_rays_hierarchical)."""
    t_near, t_far = ray_aabb_segment(rays_o, rays_d, aabb, near, far)
    out = render_rays_hierarchical(
        rays_o, rays_d, near=t_near, far=t_far, n_fine=field.n_fine, background=background,
        coarse_sampler=StratifiedSampler(n_samples=field.n_coarse, jitter=jitter, generator=generator),
        coarse_fn=_rgb_sigma(field.coarse, field.view_dependent), fine_fn=_rgb_sigma(field.fine, field.view_dependent),
        jitter=jitter, generator=generator,
    )  # fmt: skip
    out["rgb_coarse"] = out["coarse"]["rgb"]
    out["samples"] = torch.tensor(float(out["coarse"]["t_starts"].numel() + out["t_starts"].numel()))
    return out


@dataclass
class FieldModel:
    field: Field
    grid: OccupancyGrid | None
    kind: str
    step_size: float  # training march step (inference: step_size * render_step_factor)
    near: float
    far: float
    aabb: Tensor  # [2, 3] the field's box: scene frame, or NDC space when ndc is set
    ndc: NDC | None = None
    render_step_factor: float = 1.0
    contraction: Contraction | None = None
    background: Background | None = None
    appearance: Appearance | None = None  # per-image colour codes (train --appearance; model.appearance)

    @property
    def chunk(self) -> int:
        """Rays per evaluation chunk (vanilla: 256 samples x 256 activations per ray)."""
        return 8192 if self.kind == "fast" else 1024

    def render(
        self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen=None, median=False, view=None,
        infer: Inference | None = Inference(),
    ):  # fmt: skip
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
        if self.ndc is None:
            return self._render(o, d, background, train=train, gen=gen, median=median, infer=infer)
        o_n, d_n, valid = self.ndc.rays_to_ndc(o, d)
        out = self._render(o_n, d_n, background, train=train, gen=gen, median=median, infer=infer)
        for key in ("depth", "depth_median"):
            if key in out:
                out[key] = self.ndc.world_t(o, d, o_n, d_n, out[key])
        if not bool(valid.all()):  # rays away from the reference view see nothing (the dummy ray misses)
            out["depth"] = torch.where(valid, out["depth"], torch.zeros_like(out["depth"]))
        return out

    def distortion(self, out: dict, o: Tensor, d: Tensor) -> Tensor:
        """mip-NeRF 360's distortion loss of a training render `out` of rays o, d [R, 3], in the normalised
        warped distance (radiance.contraction.normalized_distance). Contracted scenes only: the fog it removes
        is what a short real capture grows near its cameras."""
        if self.contraction is None or self.kind != "fast":
            raise ValueError("distortion: expected a fast field in a contracted scene")
        idx = out["ray_indices"]
        s0 = normalized_distance(self.contraction, o, d, self.near, out["t_starts"], idx)
        s1 = normalized_distance(self.contraction, o, d, self.near, out["t_ends"], idx)
        return distortion_loss(out["weights"], s0, s1, idx, o.shape[0])

    def _render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, gen, median, infer):
        step = self.step_size if train else self.step_size * self.render_step_factor
        fast = dict(step_size=step, background=background, jitter=train, with_median=median,
                    infer=None if train else infer)  # fmt: skip
        if self.kind == "fast" and self.contraction is not None:
            return _render_fast_contracted(self.field, self.grid, self.contraction, o, d, near=self.near, **fast)
        if self.kind == "fast":
            return _render_fast(self.field, self.grid, o, d, near=self.near, far=self.far, **fast)
        return _render_vanilla(self.field, o, d, aabb=self.aabb, near=self.near, far=self.far, background=background,
                              jitter=train, generator=gen)  # fmt: skip


EMPTY_OPACITY = 0.003
"""Opacity of one training step below which an occupancy cell counts as empty. tiny npz, 120 s (loaded machine):
0.01 -> 30.81 dB, 0.003 -> 30.98 dB; the NDC test scene: 0.01 empties cells before the far wall is learned (22.5 dB,
depth off by 50 %), 0.003 -> 24.4 dB, 7.9 %."""


def _step_size(aabb: Tensor, resolution: int, ratio: float) -> float:
    return float((aabb[1] - aabb[0]).mean()) / resolution * ratio


def choose_scene_model(scene_model: str, scene: Scene, *, plain_background: bool) -> tuple[str, str]:
    """(box | ndc | contract, why). "auto": ndc when the cameras are forward-facing (all within 45 degrees of
    their mean direction); box when the photos have alpha or a plain background colour (nothing to model
    outside the object's box); contract otherwise (real photos see a background beyond the box)."""
    if scene_model != "auto":
        return scene_model, f"asked for (scene_model={scene_model})"
    if is_forward_facing(scene):
        return "ndc", "forward-facing cameras (all within 45 degrees of their mean direction)"
    if plain_background:
        return "box", "images with alpha or a plain background colour: nothing to model outside the box"
    return "contract", "opaque photos whose background is not a plain colour: space beyond the box is contracted"


def scene_ndc(scene: Scene) -> NDC:
    """NDC of the scene's mean camera; its near plane is the scene's near bound."""
    if not (scene.near > 0 and math.isfinite(scene.near)):
        raise UserError(f"{scene.root}: NDC needs a near bound > 0 in transforms.json, got near={scene.near}")
    return fit_ndc(np.stack([f.world_from_cam for f in scene.frames]), scene.frame_intrinsics(0), scene.near)


def build_model(
    settings: ModelSettings,
    scene: Scene,
    device: torch.device,
    field_cfg: dict | None,
    ndc: NDC | None = None,
    contraction: Contraction | None = None,
    background: Background | None = None,
) -> FieldModel:
    """The field, its occupancy grid (fast) and render settings. With `ndc`, the field's box is the NDC box
    of the training cameras (near 0, far: the box's end at infinity); with `contraction`, the contracted cube
    [-2, 2]^3 around the scene's box; otherwise the scene's aabb. `field_cfg` (a checkpoint's) rebuilds a saved
    field; None makes a new one from `settings`."""
    if ndc is not None and contraction is not None:
        raise ValueError("expected at most one of ndc and contraction")
    if contraction is not None and settings.field != "fast":
        raise UserError("scene_model contract needs the fast field (vanilla samples the box only)")
    if ndc is not None:
        poses = np.stack([f.world_from_cam for f in scene.frames])
        intr = [scene.frame_intrinsics(i) for i in range(len(scene.frames))]
        aabb = torch.as_tensor(ndc.box(poses, intr), dtype=torch.float32)
        near, far = 0.0, 1e10
    elif contraction is not None:
        aabb = torch.tensor(CONTRACTED_BOX, dtype=torch.float32)
        near, far = float(scene.near), 1e10
    else:
        aabb = torch.as_tensor(scene.aabb, dtype=torch.float32).reshape(2, 3)
        near, far = float(scene.near), (scene.far if math.isfinite(scene.far) else 1e10)
    view_dep = True if settings.view_dependent is None else settings.view_dependent
    if field_cfg is None:
        if settings.field == "fast":
            field_cfg = TensoRF(aabb=aabb, resolution=settings.resolution[0], view_dependent=view_dep).config()
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
    if contraction is not None:  # contracted units -> scene units inside the inner box
        step *= float(contraction.half.mean())
    background = background if background is not None else Background("fixed")
    return FieldModel(field, grid, field_cfg["kind"], step, near, float(far), aabb.to(device), ndc,
                      settings.render_step_factor, contraction, background.to(device))  # fmt: skip
