"""Defaults `train` finds from the data and the device, each with its reason for the manifest.

One rule, written once, for both devices:
- **Background** (`--background auto`): photos with alpha train on a random colour per ray and are evaluated on
  white; opaque photos whose border pixels (2-pixel frame of every training view) are >= 90 % one colour (each
  channel within 4/255 of the median border colour: tiny-NeRF's black, renders on white) get alpha 0 on the pixels
  of that colour and train the same way (a fixed colour gives empty space no reason to empty: a dark fog matches
  black as well) and are evaluated on that colour; other opaque photos train on a random colour per ray too
  (instant-ngp's choice: the field must explain every pixel) and are shown on the border's median colour. Learning
  the colour was measured worse (docs/DESIGN.md, "Backgrounds").
- **Scene model** (`--scene-model auto`, `model.spaces.choose_space`): NDC for forward-facing captures, the box for
  alpha or a plain background, contraction otherwise (`radiance.space`). The method may keep another (the nerf
  method takes straight rays in a box only) and says why.
- **The method's options** (`--method`, `model.methods`): each method resolves its own (`Method.prepare`: the
  density field's grid, march and priors per kind of scene space, `model.methods.density.rules`).
- **Batch** (`--batch-rays`): 1024 rays on CPU (more small steps beat fewer big ones in a fixed time), 8192 on CUDA.
- **Learning rate** (`--lr`): the method's (`Method.default_lr`).
- **Downscale** (`--downscale`, `resolve_downscale`: read before the images are), the final evaluation's view count
  (`final_eval_views`: after training, from the render speed measured), threads (torch's).

`resolve_defaults` returns the Config with every None replaced (`Defaults.config`: what config.json records and the
loop reads; final_eval_views joins it at the end), with the reason of each in the manifest's `used.defaults`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import torch

from nerfpipe.data.transforms import Scene
from nerfpipe.model.background import Background
from nerfpipe.model.methods import Method, Prepared, TrainContext, method_named
from nerfpipe.model.spaces import choose_space
from nerfpipe.model.views import Views, auto_downscale
from nerfpipe.radiance.space import Space
from nerfpipe.stages.train.background import background_conflict, choose_background
from nerfpipe.stages.train.config import Config, method_options

__all__ = ["Defaults", "Photos", "resolve_defaults", "resolve_downscale", "final_eval_stride"]


@dataclass(frozen=True)
class Defaults:
    config: Config
    """The Config with every None resolved (final_eval_views: chosen at the end of the run, `final_eval_views`), its
    `options` the method's resolved options."""
    context: TrainContext
    """What the method was given: the scene, its views, the device, the background and the scene model's choice."""
    prepared: Prepared
    """The method's resolved options and the space its model lives in."""
    plain_background: bool
    reasons: dict[str, str]
    """Why each value is what it is (the manifest's `used.defaults`)."""
    plain_colour: tuple[float, float, float] | None = None

    @property
    def background(self) -> Background:
        return self.context.background

    @property
    def space(self) -> Space | None:
        return self.prepared.space


def resolve_downscale(config: Config, scene: Scene, train_idx: tuple[int, ...], device: torch.device) -> float:
    """`Config.downscale`, else the smallest power of two that brings the long side to <= 800 px on CPU, 1600 px on
    CUDA (before the images are read: they are read at this size)."""
    return config.downscale or auto_downscale(scene, train_idx, _max_side(device))


def _max_side(device: torch.device) -> int:
    return 1600 if device.type == "cuda" else 800


@dataclass(frozen=True)
class Photos:
    """The scene and its photos as `resolve_defaults` reads them."""

    scene: Scene
    train: Views
    test: Views | None
    train_idx: tuple[int, ...]


def resolve_defaults(config: Config, photos: Photos, device: torch.device, downscale: float) -> Defaults:
    """The Config with its None values resolved from the scene, its training views (read at `downscale`, from
    `resolve_downscale`) and the device (see the module doc): the background, then the scene model's space, then
    the method's options, the batch, learning rate and threads. UserError when an option is given that the scene
    cannot take."""
    scene, views = photos.scene, photos.train
    has_alpha = scene.has_alpha or views.any_transparent()
    background, plain, bg_reason = choose_background(config.background, views, has_alpha)
    background = background.to(device)  # every method's model holds it: its colours join the batch's device
    why = " (asked for)" if config.downscale else f": long side <= {_max_side(device)} px"
    reasons = {"background": bg_reason, "downscale": f"{downscale:g}{why}"}
    conflict = background_conflict(config.background, views, has_alpha)
    if conflict is not None:
        reasons["background_conflict"] = conflict
    kind, kind_why = choose_space(config.scene_model, scene, plain_background=plain)
    context = TrainContext(
        scene=scene,
        train=views,
        test=photos.test,
        train_idx=tuple(photos.train_idx),
        device=device,
        downscale=downscale,
        background=background,
        space_kind=kind,
        space_why=kind_why,
        refine_poses=config.refine is not None,
    )
    method = method_named(config.method)
    prepared = method.prepare(context, method_options(config), reasons)
    run = _run_options(config, method, device.type == "cuda", reasons)
    resolved = dataclasses.replace(config, options=prepared.options, downscale=downscale, **run)
    plain_colour = None
    if config.background == "auto" and plain and not has_alpha:
        plain_colour = tuple(float(v) for v in background.eval_colour())
    return Defaults(
        config=resolved,
        context=context,
        prepared=prepared,
        plain_background=plain,
        reasons=reasons,
        plain_colour=plain_colour,
    )


def _run_options(config: Config, method: Method, cuda: bool, reasons: dict[str, str]) -> dict[str, Any]:
    """Batch, learning rate and threads: as given, else the device's and the method's rules."""
    if config.batch_rays is not None:
        batch, reasons["batch_rays"] = int(config.batch_rays), "asked for"
    elif (own := method.default_batch(cuda)) is not None:
        batch, reasons["batch_rays"] = own
    else:
        batch = 8192 if cuda else 1024
        reasons["batch_rays"] = "8192 on CUDA, 1024 on CPU (more small steps in a fixed time)"
    lr, reasons["lr"] = (float(config.lr), "asked for") if config.lr is not None else method.default_lr()
    threads = config.threads if config.threads is not None else torch.get_num_threads()
    return {"batch_rays": batch, "lr": lr, "threads": threads}


MIN_SCORED_PIXELS = 4096
"""Pixels of a test view the end-of-run PSNR scores at least (a stride never leaves fewer): about 0.1 dB of
sampling spread for a view's PSNR."""


def final_eval_stride(config: Config, n_views: int, rays_per_second: float, pixels_per_view: float) -> int:
    """The pixel stride of the end-of-run PSNR when `Config.final_eval_views` is None: every test view is scored
    (a few hand-picked ones told a phone capture's user 30.5 dB where `eval` over its 23 views said 23.98), on every
    stride-th pixel of each, the stride that fits final_eval_fraction x max_seconds at the render speed measured;
    1 (whole images) when they all fit, never so large that a view keeps fewer than MIN_SCORED_PIXELS."""
    fit = config.final_eval_fraction * config.max_seconds * rays_per_second
    stride = max(1, math.ceil(n_views * pixels_per_view / max(fit, 1.0)))
    return max(1, min(stride, int(pixels_per_view // MIN_SCORED_PIXELS)))
