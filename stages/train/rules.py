"""`train`'s rules per kind of scene space (`RULES`, keyed by the space's class): the fast field's grid, march,
components, density activation, colour MLP width and TV prior, each measured on real captures of its own kind. No
rule measured on one kind of capture applies to another; `stages.train.defaults` applies them (a value given on the
command line wins) and writes each reason into the manifest.

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
  2 voxels on CPU. TV 0.01 (TensoRF's real-capture setting: fox held-out 13.7 -> 17.8 dB). Density softplus, as for
  objects: NDC's relu on the fox (`train --max-seconds 300 --density-activation relu`, then `eval`, 2026-11-28) gave
  27.32 dB / 0.774 in 2,448 steps, against the make chain's 27.42 / 0.781 in 2,686 with softplus.
- **NDC scenes (forward-facing captures; measured on the LLFF fern)**, `NDCRules`: the field's x, y span the
  mean camera's image, so the grid follows the training image's width in pixels, not an object's size:
  one voxel every NDC_PIXELS_PER_VOXEL pixels of the image width, clamped to [NDC_MIN, NDC_MAX], start NDC_START; z'
  (inverse depth) needs far fewer steps than x, y have texels, so the march takes NDC_SAMPLES steps across z'
  in [-1, 1] whatever the grid (the object rule gave fern 207 samples a ray: 1,112 steps in 300 s, 17.99 dB),
  but no finer than NDC_MIN_STEP_VOXELS voxel: the occupancy grid's empty rule is an opacity per step, so steps
  much finer than the grid empty every cell before the field has grown (the 48 px forward test scene at a 48 grid:
  0.6 voxel 23.1 dB, 0.4 voxel 9.6 dB). NDC_RANK: TensoRF's LLFF components, most on the xy (image) plane
  (16,48 on every plane cost steps the fern needs more). TV NDC_TV. Density through NDC_ACTIVATION (relu, TensoRF's
  LLFF setting) instead of the objects' softplus. The colour MLP stays DEFAULT_HIDDEN (64) wide, as for the other
  kinds: TensoRF's LLFF 128 gained 0.1 dB on the fern and cost 27 % of the render speed. Figures in NDCRules'
  docstring.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nerfpipe.data.transforms import Scene
from nerfpipe.radiance.fields.fast import DEFAULT_HIDDEN, TENSORF_RANK
from nerfpipe.radiance.space import Box, Contracted, NDCSpace, Space

__all__ = ["RULES", "BoxRules", "ContractRules", "NDCRules", "Need", "object_size_px"]


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

    def density_activation(self) -> tuple[str, str]:
        return "softplus", "softplus with shift -10 (TensoRF's for objects; NDC's relu was no better on the fox)"

    def mlp_width(self) -> tuple[int, str]:
        return DEFAULT_HIDDEN, f"{DEFAULT_HIDDEN} (the object and contracted scenes' settings were measured with it)"


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
NDC_SAMPLES = 48
NDC_RANK = (16, 4, 4, 48, 12, 12)
NDC_MIN_STEP_VOXELS = 1.0
NDC_TV = 0.01
NDC_ACTIVATION = "relu"


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
    again; the chain's figure is in docs/BENCH_REAL.md.
    Then (2026-11-28) the density activation: relu(f) (TensoRF's LLFF setting) against the objects' softplus(f - 10).
    Fern `--max-steps 2000 --threads 1`, two runs side by side, train's own evaluation of the 3 hold-out views; the 48
    px forward scene as above, seeds 0 and 1; the fern's make chain (300 s, `eval`, docs/BENCH_REAL.md):
    | activation        | fern 2,000 steps | 48 px: 400 steps | 20 s          | fern chain: steps, held-out |
    | softplus(f - 10)  | 21.79 dB         | 23.66 / 22.97 dB | 25.76 / 25.74 | 4,930, 24.28 dB / 0.757     |
    | relu <- this rule | 23.06 dB         | 25.17 / 24.97 dB | 25.92 / 25.66 | 6,345, 24.55 dB / 0.766     |
    relu is ahead at every periodic evaluation of the fern (0.9-1.3 dB from step 500); by 300 s the lead is 0.27 dB.
    Its exact zeros let the occupancy grid skip 43 % of the samples (24 % with softplus), hence the steps. With them
    a finer march costs less than before; relu, `train --max-seconds 300`, then `eval` (32 steps: the chain above):
    | steps across z'  | steps in 300 s | held-out PSNR / SSIM | 48 px scene (seed 0): 400 steps | 20 s     |
    | 32               | 6,345          | 24.55 dB / 0.766     | 25.08 dB                        | 26.44 dB |
    | 48 <- this rule  | 5,099          | 24.82 dB / 0.779     | 25.09 dB                        | 26.21 dB |
    | 64               | 4,642          | 24.71 dB / 0.782     | 25.06 dB                        | 26.34 dB |
    (On the 48 px scene's 48 grid, 48 and 64 steps both reach the floor of one voxel.)
    Then (2026-11-28) the colour MLP's width (`--mlp-width`), 128 (TensoRF's LLFF featureC) against 64
    (DEFAULT_HIDDEN), same command, each fern row two runs; the 48 px forward scene as above, seeds 0 / 1:
    | MLP width       | fern steps in 300 s | fern held-out PSNR | 48 px: 400 steps | 20 s (steps)              |
    | 64 <- this rule | 5,099 / 5,719       | 24.82 / 24.84 dB   | 24.91 / 25.07 dB | 26.35 / 25.54 (1192/1121) |
    | 128             | 4,984 / 4,824       | 24.94 / 24.93 dB   | 25.17 / 24.96 dB | 25.95 / 25.77 (919/967)   |
    The fern's make chain with 128 (bench_real --only fern at 98000db): 24.89 dB / 0.782 in 5,028 steps (24.82 /
    0.778 with 64), eval 51.4k rays/s (70.9k with 64), and the video, fitted to the same render budget, 397x298
    instead of 457x343. 0.07-0.1 dB, inside the noise of one run, against a quarter of the render speed: not the
    default; `--mlp-width 128` asks for it.
    Also tried (fern, single runs, none beyond the noise): view directions without their encoding (TensoRF's LLFF
    view_pe 0) 24.85 dB at 64, 24.87 at 128; `--upsample-at 0.1,0.2,0.3,0.4` 24.88 at 64, 24.94 at 128;
    `--upsample-at 0.03,0.06,0.12,0.2` 24.79; `--lr-decay 0.03` 24.86."""

    def resolution(self, need: Need) -> tuple[tuple[int, int], str]:
        side = _ndc_box_side(need.space)
        width = float(np.median([need.scene.frame_intrinsics(i).w for i in need.train_idx])) / need.downscale
        r1 = int(min(NDC_MAX, max(NDC_MIN, round(side * width / (2.0 * NDC_PIXELS_PER_VOXEL)))))
        r0 = min(NDC_START, r1)
        why = (
            f"image {width:.0f} px wide: a voxel every {NDC_PIXELS_PER_VOXEL:g} px across it (NDC box side "
            f"{side:.2f}), final in [{NDC_MIN}, {NDC_MAX}], start {r0}"
        )
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
        why = (
            f"TensoRF's LLFF components: density {d[0]} on the xy (image) plane, {d[1]} and {d[2]} on xz and yz; "
            f"appearance {a[0]}, {a[1]}, {a[2]} (a step's cost follows the planes' size)"
        )
        return NDC_RANK, why

    def density_activation(self) -> tuple[str, str]:
        return NDC_ACTIVATION, f"{NDC_ACTIVATION} (TensoRF's LLFF setting: fern +1.3 dB at 2,000 steps, see NDCRules)"

    def mlp_width(self) -> tuple[int, str]:
        why = f"{DEFAULT_HIDDEN} (TensoRF's LLFF 128: fern +0.1 dB but renders 27 % slower, see NDCRules)"
        return DEFAULT_HIDDEN, why


def _ndc_box_side(space: NDCSpace) -> float:
    """Mean side of the NDC box the field spans (float64, as `radiance.ndc.NDC.box` gives it), for both NDC rules."""
    lo, hi = np.asarray(space.box, dtype=np.float64)
    return float(np.mean(hi - lo))


RULES: dict[type[Space], BoxRules | NDCRules] = {Box: BoxRules(), NDCSpace: NDCRules(), Contracted: ContractRules()}
"""Each kind of scene space's grid, step and prior rules."""
