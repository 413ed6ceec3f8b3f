"""Defaults `train` finds from the data and the device, each with its reason for the manifest.

One rule, written once, for both devices:
- **Background** (`--background auto`): photos with alpha train on a random colour per ray and are evaluated on
  white; opaque photos whose border pixels (2-pixel frame of every training view) are >= 90 % one colour (each
  channel within 4/255 of the median border colour: tiny-NeRF's black, renders on white) get alpha 0 on the pixels
  of that colour and train the same way (a fixed colour gives empty space no reason to empty: a dark fog matches
  black as well; tiny npz, 60 s, one thread: 20.73 dB fixed vs 23.47 dB this way) and are evaluated on that
  colour; other opaque photos train on a random colour per ray too (instant-ngp's choice: the field must explain
  every pixel) and are shown on the border's median colour. Decision against the issue's "otherwise learn a
  colour", measured on the forward-facing test scene (48 px, 400 steps): fixed white 24.64 dB, random 24.58 dB,
  learned 21.67 dB (the learned colour went dark and the field transparent).
- **Scene model** (`--scene-model auto`, `model.field_model.choose_space`): NDC for forward-facing captures, the
  box for alpha or a plain background, contraction otherwise (`radiance.space`). The space is made before the
  grid, step and priors, which are then its kind's own (`RULES`, keyed by the space's class): no rule measured on
  one kind of capture applies to another.
- **Grid, march, components, density activation and TV per kind of scene**: `stages.train.rules` (box, contracted
  and NDC scenes, each rule with the captures it was measured on).
- **Pose refinement** (`--refine-poses`): coarse-to-fine as BARF anneals its frequencies, in the grid's terms
  (its resolution is its frequency band): the grid starts at a quarter of the final size (at least 16) and is
  upsampled at `REFINE_UPSAMPLE_AT` instead of `UPSAMPLE_AT`, so the cameras first register to a smooth field.
  48 px scene, 3 deg / 3 % perturbations, 400 steps: median rotation error 1.40 deg with the usual (64, 96) grid
  upsampled at 5-30 %, 0.84 deg with (24, 96) upsampled at 20-50 %.
- **Batch** (`--batch-rays`): 1024 rays on CPU (more small steps beat fewer big ones in a fixed time: 22.6 vs
  18.1 dB after 30 s on a 128 px scene), 8192 on CUDA (issue 14's H100 figure).
- **Learning rate** (`--lr`, `LR`): 0.03 for the fast field (its MLP at lr/20), 5e-4 for the vanilla field.
- **Depth loss** (`--depth-loss`): DEPTH_LOSS where the scene has sparse points and the field is fast and
  contracted, else 0; **downscale** (`--downscale`, `resolve_downscale`: read before the images are), the final
  evaluation's view count (`final_eval_views`: after training, from the render speed measured), threads (torch's).

`resolve_defaults` returns the Config with every None replaced (`Defaults.config`: what config.json records and the
loop reads; final_eval_views joins it at the end), with the reason of each in the manifest's `used.defaults`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.sparse_depth import KEY as SPARSE_KEY
from nerfpipe.data.transforms import Scene
from nerfpipe.model.background import Background
from nerfpipe.model.field_model import choose_space, make_space
from nerfpipe.radiance.space import Box, Space
from nerfpipe.stages.train.background import choose_background
from nerfpipe.stages.train.config import Config, FastOptions
from nerfpipe.stages.train.rules import RULES, BoxRules, NDCRules, Need
from nerfpipe.stages.train.views import DepthRays, Views, auto_downscale, sparse_depth_rays

__all__ = [
    "UPSAMPLE_AT",
    "REFINE_UPSAMPLE_AT",
    "Defaults",
    "resolve_defaults",
    "resolve_downscale",
    "final_eval_views",
    "DEPTH_LOSS",
    "LR",
]

UPSAMPLE_AT = (0.05, 0.1, 0.2, 0.3)
"""Run-progress fractions of the grid upsamplings (fast field)."""
REFINE_UPSAMPLE_AT = (0.2, 0.3, 0.4, 0.5)
"""The same with --refine-poses: the grid stays coarse while the cameras move most."""
DEPTH_LOSS = 0.01
"""Default `--depth-loss` weight where sparse points exist (contracted scenes)."""
LR = {
    "fast": (0.03, "0.03 for the fast field's grids (its MLP at lr/20)"),
    "vanilla": (5e-4, "5e-4 for the vanilla field's MLPs"),
}
"""Each field's learning rate and its reason (`Config.lr`)."""


@dataclass(frozen=True)
class Defaults:
    config: Config
    """The Config with every None resolved (final_eval_views: chosen at the end of the run, `final_eval_views`)."""
    space: Space
    """The scene space the field lives in (`radiance.space`)."""
    background: Background
    plain_background: bool
    reasons: dict[str, str]
    """Why each value is what it is (the manifest's `used.defaults`)."""
    plain_colour: tuple[float, float, float] | None = None
    depth_rays: DepthRays | None = None
    """Rays through the training photos' sparse points, where the depth loss is on."""


def resolve_downscale(config: Config, scene: Scene, train_idx: tuple[int, ...], device: torch.device) -> float:
    """`Config.downscale`, else the smallest power of two that brings the long side to <= 800 px on CPU, 1600 px on
    CUDA (before the images are read: they are read at this size)."""
    return config.downscale or auto_downscale(scene, train_idx, _max_side(device))


def _max_side(device: torch.device) -> int:
    return 1600 if device.type == "cuda" else 800


def resolve_defaults(
    config: Config, scene: Scene, views: Views, train_idx: tuple[int, ...], device: torch.device, downscale: float
) -> Defaults:
    """The Config with its None values resolved from the scene, its training views (read at `downscale`, from
    `resolve_downscale`) and the device (see the module doc): the background, then the scene space, then its
    kind's grid, step and priors, the depth loss, the batch, learning rate and threads. UserError when a loss
    weight is given for a scene that cannot take it."""
    has_alpha = scene.has_alpha or views.any_transparent()
    background, plain, bg_reason = choose_background(config.background, views, has_alpha)
    why = " (asked for)" if config.downscale else f": long side <= {_max_side(device)} px"
    reasons = {"background": bg_reason, "downscale": f"{downscale:g}{why}"}
    kind, space = _space(config, scene, plain, reasons)
    need = Need(
        scene=scene,
        space=space,
        train_idx=tuple(train_idx),
        downscale=downscale,
        cuda=device.type == "cuda",
        refine_poses=config.refine is not None,
    )
    fast = _fast_options(config.fast, RULES[kind], need, reasons)
    rays, fast = _depth_loss(config.field, fast, scene, need.train_idx, space, reasons)
    resolved = dataclasses.replace(config, fast=fast, downscale=downscale, **_run_options(config, need.cuda, reasons))
    plain_colour = None
    if config.background == "auto" and plain and not has_alpha:
        plain_colour = tuple(float(v) for v in background.eval_colour())
    return Defaults(
        config=resolved,
        space=space,
        background=background,
        plain_background=plain,
        reasons=reasons,
        plain_colour=plain_colour,
        depth_rays=rays,
    )


def _space(config: Config, scene: Scene, plain: bool, reasons: dict[str, str]) -> tuple[type[Space], Space]:
    """The scene space's kind (the vanilla field takes straight rays in a box only) and the space."""
    kind, kind_why = choose_space(config.scene_model, scene, plain_background=plain)
    if not kind.straight_rays and config.field != "fast":
        kind, kind_why = Box, f"the vanilla field samples straight rays in a box (no {kind.name} space)"
    reasons["scene_model"] = f"{kind.name}: {kind_why}"
    return kind, make_space(kind, scene)


def _fast_options(fast: FastOptions, rules: BoxRules | NDCRules, need: Need, reasons: dict[str, str]) -> FastOptions:
    """The fast group's grid, schedule, step and TV: as given, else the scene kind's rules."""
    resolution, upsample_at = _grid(fast, rules, need, reasons)
    if fast.step_ratio is not None:
        step_ratio, reasons["step_ratio"] = float(fast.step_ratio), "asked for"
    else:
        step_ratio, reasons["step_ratio"] = rules.step_ratio(resolution, need)
    tv, reasons["tv"] = (float(fast.tv), "given") if fast.tv is not None else rules.tv()
    rank, reasons["rank"] = (tuple(fast.rank), "asked for") if fast.rank is not None else rules.rank()
    act = fast.density_activation
    act, reasons["density_activation"] = (act, "asked for") if act is not None else rules.density_activation()
    width = fast.mlp_width
    width, reasons["mlp_width"] = (width, "asked for") if width is not None else rules.mlp_width()
    return dataclasses.replace(
        fast,
        resolution=resolution,
        rank=rank,
        upsample_at=upsample_at,
        step_ratio=step_ratio,
        tv=tv,
        density_activation=act,
        mlp_width=width,
    )


def _grid(
    fast: FastOptions, rules: BoxRules | NDCRules, need: Need, reasons: dict[str, str]
) -> tuple[tuple[int, int], tuple[float, ...]]:
    """The grid's start and final resolution and its upsampling fractions (coarse-to-fine with pose refinement)."""
    if fast.resolution is not None:
        resolution, reasons["resolution"] = tuple(fast.resolution), "asked for"
    else:
        (r0, r1), reasons["resolution"] = rules.resolution(need)
        if need.refine_poses:
            r0 = max(16, round(r1 / 4))
            reasons["resolution"] += "; --refine-poses: start at a quarter of the final size (coarse-to-fine)"
        resolution = (r0, r1)
    if fast.upsample_at is not None:
        upsample_at, reasons["upsample_at"] = tuple(fast.upsample_at), "asked for"
    elif need.refine_poses:
        upsample_at = REFINE_UPSAMPLE_AT
        reasons["upsample_at"] = "--refine-poses: later upsamplings, the cameras register to a coarse grid first"
    else:
        upsample_at = UPSAMPLE_AT
    return resolution, upsample_at


def _depth_loss(
    field: str, fast: FastOptions, scene: Scene, train_idx: tuple[int, ...], space: Space, reasons: dict[str, str]
) -> tuple[DepthRays | None, FastOptions]:
    """The rays through the training photos' sparse points (or None) and `fast` with the depth loss's weight:
    as given, else DEPTH_LOSS where the scene has sparse points and a fast contracted field, else 0."""
    given, rel = fast.depth_loss, scene.extra.get(SPARSE_KEY)
    rays, weight = None, 0.0
    if given == 0:
        reasons["depth_loss"] = "off (given)"
    elif rel is None or not space.sparse_depth or field != "fast":
        reasons["depth_loss"] = "left out: " + (
            f"no {SPARSE_KEY} in transforms.json (sparse points come from COLMAP through convert)"
            if rel is None
            else f"applies to fast contracted scenes only (this one: {field}, {space.name})"
        )
    elif (rays := sparse_depth_rays(scene, rel, train_idx)) is None:
        reasons["depth_loss"] = f"left out: {rel} has no points observed by the training photos"
    else:
        weight = given if given is not None else DEPTH_LOSS
        reasons["depth_loss"] = (
            f"{weight} on {rays.depth.numel()} sparse-point rays of {len(train_idx)} training photos"
        )
    if given and rays is None:
        raise UserError(f"--depth-loss: {reasons['depth_loss'].removeprefix('left out: ')}")
    return rays, dataclasses.replace(fast, depth_loss=weight)


def _run_options(config: Config, cuda: bool, reasons: dict[str, str]) -> dict[str, Any]:
    """Batch, learning rate, view dependence and threads: as given, else the device's and the field's rules."""
    if config.batch_rays is not None:
        batch, reasons["batch_rays"] = int(config.batch_rays), "asked for"
    else:
        batch = 8192 if cuda else 1024
        reasons["batch_rays"] = "8192 on CUDA, 1024 on CPU (more small steps in a fixed time)"
    lr, reasons["lr"] = (float(config.lr), "asked for") if config.lr is not None else LR[config.field]
    view_dependent = True if config.view_dependent is None else config.view_dependent
    threads = config.threads if config.threads is not None else torch.get_num_threads()
    return {"batch_rays": batch, "lr": lr, "view_dependent": view_dependent, "threads": threads}


def final_eval_views(config: Config, n_views: int, rays_per_second: float, pixels_per_view: float) -> int:
    """How many test views the end of the run renders in full when `Config.final_eval_views` is None: as many as
    fit in final_eval_fraction x max_seconds at the render speed measured, at least 1, at most n_views."""
    fit = int(config.final_eval_fraction * config.max_seconds * rays_per_second / pixels_per_view)
    return max(1, min(n_views, fit))
