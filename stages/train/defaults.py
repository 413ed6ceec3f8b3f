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
- **Box scenes (objects; measured on lego_100, lego_400, the synthetic scenes)**, `BoxRules`: final grid 1.6 x the
  object's size in pixels (the scene box's longest side projected at the median camera distance with the median
  focal length, at most the image's long side), clamped to [96, 300]; the start size is 0.32 x that, clamped to
  [64, 128]. Measured on CPU: lego_100 (box ~100 px) -> (64, 160) was the best of (48, 128), (64, 160), (64, 192)
  in 120 s; lego_400 (box ~400 px) -> (96, 300) gave 32.5 dB in 900 s. On CUDA the start size is at least 128
  (issue 14's H100 measurement: (128, 300) with 8192 rays, 33.9 dB vs 28.3 dB for (64, 160) in 240 s). March: 2
  voxels of the final grid below 200 voxels, 1 from there on (lego_400 used 1 at 300). No TV prior (objects on a
  clean background have no sparsely seen space to fill).
- **Contracted scenes (unbounded real captures; measured on the fox)**, `ContractRules`: the box rule doubled (half
  the grid covers the inner box), final at most 256 on CPU and 384 on CUDA, start at most 128; the march stays
  2 voxels on CPU. TV 0.01 (TensoRF's real-capture setting: fox held-out 13.7 -> 17.8 dB).
- **NDC scenes (forward-facing captures; measured on the LLFF fern)**, `NDCRules`: the field's x, y span the
  mean camera's image, so the grid follows the training image's width in pixels, not an object's size:
  one voxel every NDC_PIXELS_PER_VOXEL pixels of the image width, clamped to [NDC_MIN, NDC_MAX], start NDC_START; z'
  (inverse depth) needs far fewer steps than x, y have texels, so the march takes NDC_SAMPLES steps across z'
  in [-1, 1] whatever the grid (the object rule gave fern 207 samples a ray: 1,112 steps in 300 s, 17.99 dB),
  but no finer than NDC_MIN_STEP_VOXELS voxel: the occupancy grid's empty rule is an opacity per step, so steps
  much finer than the grid empty every cell before the field has grown (the 48 px forward test scene at a 48 grid:
  0.6 voxel 23.1 dB, 0.4 voxel 9.6 dB). NDC_RANK: TensoRF's LLFF components, most on the xy (image) plane
  (16,48 on every plane cost steps the fern needs more). TV NDC_TV. Figures in NDCRules' docstring.
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

import numpy as np
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.sparse_depth import KEY as SPARSE_KEY
from nerfpipe.data.transforms import Scene
from nerfpipe.model.background import Background
from nerfpipe.model.field_model import choose_space, make_space
from nerfpipe.radiance.fields.fast import TENSORF_RANK
from nerfpipe.radiance.space import Box, Contracted, NDCSpace, Space
from nerfpipe.stages.train.background import choose_background
from nerfpipe.stages.train.config import Config, FastOptions
from nerfpipe.stages.train.views import DepthRays, Views, auto_downscale, sparse_depth_rays

__all__ = [
    "UPSAMPLE_AT",
    "REFINE_UPSAMPLE_AT",
    "RULES",
    "BoxRules",
    "NDCRules",
    "ContractRules",
    "Defaults",
    "object_size_px",
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
LR = {"fast": (0.03, "0.03 for the fast field's grids (its MLP at lr/20)"),
      "vanilla": (5e-4, "5e-4 for the vanilla field's MLPs")}  # fmt: skip
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


def object_size_px(scene: Scene, train_idx: tuple[int, ...]) -> float:
    """The scene box's longest side in pixels at the median camera distance and median focal length, at most
    the images' long side (a box that fills the view is seen at the image's resolution)."""
    box = np.asarray(scene.aabb, dtype=np.float64).reshape(2, 3)
    centre, side = box.mean(0), float((box[1] - box[0]).max())
    dist = np.median([np.linalg.norm(np.asarray(scene.frames[i].world_from_cam)[:3, 3] - centre) for i in train_idx])
    focal = np.median([scene.frame_intrinsics(i).fx for i in train_idx])
    long_side = max(max(scene.frame_intrinsics(i).w, scene.frame_intrinsics(i).h) for i in train_idx)
    return float(min(focal * side / max(dist - side / 2, side / 2), long_side))


@dataclass(frozen=True)
class Need:
    """What a kind's rules read: the scene, its space, its training views' indices, the downscale and the device."""

    scene: Scene
    space: Space
    train_idx: tuple[int, ...]
    downscale: float
    cuda: bool
    refine_poses: bool


class BoxRules:
    """Objects in their box (module doc): measured on lego_100, lego_400 and the synthetic object scenes."""

    TV = 0.0

    def resolution(self, need: Need) -> tuple[tuple[int, int], str]:
        size = object_size_px(need.scene, need.train_idx) / need.downscale
        r1 = int(min(300, max(96, round(1.6 * size))))
        r0 = int(min(128, max(128 if need.cuda else 64, round(0.32 * r1))))
        return (r0, r1), f"object ~{size:.0f} px across: final 1.6 x size in [96, 300], start 0.32 x"

    def step_ratio(self, resolution: tuple[int, int], need: Need) -> tuple[float, str]:
        return (2.0 if resolution[1] < 200 else 1.0), "2 voxels below a 200 grid, 1 from there on (objects)"

    def tv(self) -> tuple[float, str]:
        return self.TV, "0 for box scenes (objects on a clean background)"

    def rank(self) -> tuple[tuple[int, ...], str]:
        density, appearance = TENSORF_RANK
        return TENSORF_RANK, f"TensoRF's {density} density and {appearance} appearance components per plane"


class ContractRules(BoxRules):
    """Unbounded captures, contracted (module doc): measured on the fox."""

    TV = 0.01

    def resolution(self, need: Need) -> tuple[tuple[int, int], str]:
        (r0, r1), why = super().resolution(need)
        cap = 384 if need.cuda else 256
        return (min(2 * r0, 128), min(2 * r1, cap)), f"{why}; doubled (half the grid covers the box), at most {cap}"

    def step_ratio(self, resolution: tuple[int, int], need: Need) -> tuple[float, str]:
        if not need.cuda:
            return 2.0, "2 voxels on CPU (a room is full of surfaces the grid cannot skip: samples bound a step)"
        ratio, _ = super().step_ratio((resolution[0], resolution[1] // 2), need)  # the box rule's grid
        return ratio, "the box rule's step on the inner box's share of the grid (CUDA)"

    def tv(self) -> tuple[float, str]:
        return self.TV, f"{self.TV} for contracted scenes (real captures: fox held-out 13.7 -> 17.8 dB)"


NDC_PIXELS_PER_VOXEL = 1.6
NDC_MIN, NDC_MAX, NDC_START = 96, 400, 64
NDC_SAMPLES = 32
NDC_RANK = (16, 4, 4, 48, 12, 12)
NDC_MIN_STEP_VOXELS = 1.0
NDC_TV = 0.01


class NDCRules:
    """Forward-facing captures in NDC (module doc): measured on the LLFF fern (images_8, 504x378, 17 training
    views, 3 held out; `convert fern --images images_8`, `train --max-steps 2000 --threads 1`, two runs side by
    side on the 2-core machine, held-out PSNR on 4096 test pixels every 250 steps, then the 3 full views):
    | final grid, march (samples a ray), TV, lr        | step 750 | step 1000 | 2000 (full views) |
    | 160, 2 voxels (62), 0.01, 0.03  <- this rule     | 20.74    | 21.00     | 21.10 dB          |
    | 160, 2 voxels (62), 0, 0.03                      | 20.28    | 20.55     | -                 |
    | 160, 2 voxels (62), 0.01, 0.02                   | 19.66    | -         | -                 |
    | 200, 64 steps (63), 0.01, 0.03                   | 20.44    | -         | -                 |
    | 300, 96 steps (96), 0.01, 0.03                   | 19.00    | -         | -                 |
    (The step-1000 and 2000 columns were read through the stale density volume that b63efaf fixed: the density
    of step 750, the first evaluation after the last upsampling; the step-750 column, where the ranking is read,
    is the current field for every row.) A finer grid learns slower per step and costs more a step (Adam over
    every texel: 17 M parameters at 300); the old object rule (300, 1 voxel, 207 samples) made 1,112 steps in 300 s
    and 17.99 dB. That table ranked the grids at step 750, and read 160 (a voxel every 4 px) as the best. At the
    budget a user runs, `train --max-seconds 300` on an idle machine (~3,000-3,900 steps), then `nerfpipe eval`,
    the ranking turns (the march is the same 64 steps across z' in every row):
    | final grid (`--resolution 64,N`) | steps in 300 s | held-out PSNR / SSIM |
    | 159 (a voxel every 4 px, before)  | 3,936 / 3,882  | 23.16 / 23.25 dB, 0.712 |
    | 224                               | 3,696          | 23.55 dB, 0.734 |
    | 300 (a voxel every 2 px: 319, clamped to NDC_MAX) <- this rule | 3,082 | 23.72 dB, 0.743 |
    | 400                               | 2,699          | 23.52 dB, 0.743 |
    By step 750 a finer grid is behind; by step 3,000 it has caught up and holds more detail. Above 300 the steps
    it costs outweigh it. Single runs (noise ~0.3 dB); the trend over four grids is what the rule rests on.
    Then (2026-11-27, same command, `eval` on the 3 hold-out views) the components and the march. A step's cost
    follows the planes' size more than the samples (dense gradients and Adam over every texel: halving the samples
    at 16,48 bought 8 % more steps), so fewer components buy many more steps; and a coarser march fits the held-out
    views better (its train PSNR is no lower):
    | rank (density, appearance), march, final grid | steps in 300 s | held-out PSNR / SSIM |
    | 16,48, 64 steps, 300 (the rule above)         | 3,005          | 23.69 dB, 0.743 (make chain) |
    | 8,24, 64 steps, 300                           | 5,128          | 23.93 dB, 0.761 |
    | 4,12, 64 steps, 300                           | 7,922          | 23.91 dB, 0.759 |
    | 4,12, 64 steps, 500                           | 6,405          | 23.92 dB, 0.773 |
    | 4,12, 128 steps, 300                          | 5,948          | 22.42 dB, 0.719 |
    | 16,48, 32 steps, 300                          | 3,256          | 23.83 dB, 0.736 |
    | 4,12, 32 steps, 300                           | 9,347          | 24.15 dB, 0.747 |
    | 4,12, 32 steps, 400 (a voxel every 1.6 px: 399) | 8,574        | 24.35 dB, 0.759 |
    | 8,24, 32 steps, 400 <- this rule              | 4,989          | 24.16 dB, 0.754 |
    | 4,12, 32 steps, 500                           | 6,722          | 24.39 dB, 0.758 |
    | 4,12, 32 steps, 400, TV 0.003 (not 0.01)      | 7,983          | 24.39 dB, 0.761 |
    Above 400, and with less TV, no gain beyond the noise; 400 is the smaller field and renders faster.
    Why 8,24 and not the fern's best 4,12: on the other forward-facing scene at hand (`scene --kind posed --layout
    forward --size 48 --views 16`, grid (24, 48), 512 rays, 2 threads) fewer components learn slower per step:
    | rank | 400 steps   | 20 s (steps)       |
    | 16,48 | 23.02 dB   | 24.59 dB (532)     |
    | 8,24  | -          | 25.89 dB (977)     |
    | 4,12  | 14.81 dB   | 24.24 dB (841)     |
    8,24 is the best there at equal time and within the noise of 4,12 on the fern (-0.19 dB, single runs).
    Then (2026-11-27, each plane with its own component count) TensoRF's own LLFF setting: 16 density and 48
    appearance components on the xy plane (NDC's x, y: the image plane, where a forward-facing capture's detail is), 4
    and 12 on xz and yz, at the cost of 8,24. Same command, fern; the 48 px forward scene as above (400 steps / 20 s):
    | rank (density, appearance)    | fern steps | fern held-out | 48 px: 400 steps | 20 s     |
    | 8,24 (the rule above)         | 4,989      | 24.16 dB      | 23.08 dB         | 25.86 dB |
    | 16,4,4,48,12,12 <- this rule  | 4,997      | 24.32 dB      | 23.66 dB         | 25.99 dB |
    Fewer texels along z' bought 10-20 % more fern steps but lost 0.4 dB on the 48 px scene (not kept). Single runs
    again; the chain's figure is in docs/BENCH_REAL.md."""

    def resolution(self, need: Need) -> tuple[tuple[int, int], str]:
        side = _ndc_box_side(need.space)
        width = float(np.median([need.scene.frame_intrinsics(i).w for i in need.train_idx])) / need.downscale
        r1 = int(min(NDC_MAX, max(NDC_MIN, round(side * width / (2.0 * NDC_PIXELS_PER_VOXEL)))))
        r0 = min(NDC_START, r1)
        why = (f"image {width:.0f} px wide: a voxel every {NDC_PIXELS_PER_VOXEL:g} px across it (NDC box side "
               f"{side:.2f}), final in [{NDC_MIN}, {NDC_MAX}], start {r0}")  # fmt: skip
        return (r0, r1), why

    def step_ratio(self, resolution: tuple[int, int], need: Need) -> tuple[float, str]:
        ratio = (2.0 / NDC_SAMPLES) / (_ndc_box_side(need.space) / resolution[1])
        why = f"{NDC_SAMPLES} steps across z' in [-1, 1] (forward-facing)"
        if ratio < NDC_MIN_STEP_VOXELS:
            ratio, why = NDC_MIN_STEP_VOXELS, f"{why}, at least {NDC_MIN_STEP_VOXELS:g} voxel (a coarse grid)"
        return ratio, why

    def tv(self) -> tuple[float, str]:
        return NDC_TV, f"{NDC_TV} for NDC scenes (forward-facing real captures)"

    def rank(self) -> tuple[tuple[int, ...], str]:
        d, a = NDC_RANK[:3], NDC_RANK[3:]
        why = (f"TensoRF's LLFF components: density {d[0]} on the xy (image) plane, {d[1]} and {d[2]} on xz and yz; "
               f"appearance {a[0]}, {a[1]}, {a[2]} (a step's cost follows the planes' size)")  # fmt: skip
        return NDC_RANK, why


def _ndc_box_side(space: NDCSpace) -> float:
    """Mean side of the NDC box the field spans (float64, as `radiance.ndc.NDC.box` gives it), for both NDC rules."""
    lo, hi = np.asarray(space.box, dtype=np.float64)
    return float(np.mean(hi - lo))


RULES: dict[type[Space], BoxRules | NDCRules] = {Box: BoxRules(), NDCSpace: NDCRules(), Contracted: ContractRules()}
"""Each kind of scene space's grid, step and prior rules."""


def resolve_downscale(config: Config, scene: Scene, train_idx: tuple[int, ...], device: torch.device) -> float:
    """`Config.downscale`, else the smallest power of two that brings the long side to <= 800 px on CPU, 1600 px on
    CUDA (before the images are read: they are read at this size)."""
    return config.downscale or auto_downscale(scene, train_idx, _max_side(device))


def _max_side(device: torch.device) -> int:
    return 1600 if device.type == "cuda" else 800


def resolve_defaults(config: Config, scene: Scene, views: Views, train_idx: tuple[int, ...], device: torch.device,
                     downscale: float) -> Defaults:  # fmt: skip
    """The Config with its None values resolved from the scene, its training views (read at `downscale`, from
    `resolve_downscale`) and the device (see the module doc): the background, then the scene space, then its
    kind's grid, step and priors, the depth loss, the batch, learning rate and threads. UserError when a loss
    weight is given for a scene that cannot take it."""
    has_alpha = scene.has_alpha or views.any_transparent()
    background, plain, bg_reason = choose_background(config.background, views, has_alpha)
    why = " (asked for)" if config.downscale else f": long side <= {_max_side(device)} px"
    reasons = {"background": bg_reason, "downscale": f"{downscale:g}{why}"}
    kind, space = _space(config, scene, plain, reasons)
    need = Need(scene=scene, space=space, train_idx=tuple(train_idx), downscale=downscale, cuda=device.type == "cuda",
                refine_poses=config.refine is not None)  # fmt: skip
    fast = _fast_options(config.fast, RULES[kind], need, reasons)
    rays, fast = _depth_loss(config.field, fast, scene, need.train_idx, space, reasons)
    resolved = dataclasses.replace(config, fast=fast, downscale=downscale, **_run_options(config, need.cuda, reasons))
    plain_colour = None
    if config.background == "auto" and plain and not has_alpha:
        plain_colour = tuple(float(v) for v in background.eval_colour())
    return Defaults(config=resolved, space=space, background=background, plain_background=plain, reasons=reasons,
                    plain_colour=plain_colour, depth_rays=rays)  # fmt: skip


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
    return dataclasses.replace(fast, resolution=resolution, rank=rank, upsample_at=upsample_at, step_ratio=step_ratio,
                               tv=tv)  # fmt: skip


def _grid(fast: FastOptions, rules: BoxRules | NDCRules, need: Need,
          reasons: dict[str, str]) -> tuple[tuple[int, int], tuple[float, ...]]:  # fmt: skip
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


def _depth_loss(field: str, fast: FastOptions, scene: Scene, train_idx: tuple[int, ...], space: Space,
                reasons: dict[str, str]) -> tuple[DepthRays | None, FastOptions]:  # fmt: skip
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
