"""The density method's rules per kind of scene space (`RULES`, keyed by the space's class): the field's grid, march,
components, density activation, colour MLP width and TV prior, each measured on real captures of its own kind. No
rule measured on one kind of capture applies to another; `model.methods.density.defaults` applies them (a value given
on the command line wins) and writes each reason into the manifest. The measurements behind each rule, with the
commands that made them, are in docs/DENSITY_RULES.md.

- **Box scenes (objects; measured on lego_100, lego_400, the synthetic scenes)**, `BoxRules`: final grid 1.6 x the
  object's size in pixels (the scene box's longest side projected at the median camera distance with the median
  focal length, at most the image's long side), clamped to [96, 300]; the start size is 0.32 x that, clamped to
  [64, 128], at least 128 on CUDA. March: 2 voxels of the final grid below 200 voxels, 1 from there on. No TV prior
  (objects on a clean background have no sparsely seen space to fill).
- **Contracted scenes (unbounded real captures; measured on the fox)**, `ContractRules`: the box rule doubled (half
  the grid covers the inner box), final at most 256 on CPU and 384 on CUDA, start at most 128; the march stays
  2 voxels on CPU. TV 0.01 (TensoRF's real-capture setting). Density softplus, as for objects.
- **NDC scenes (forward-facing captures; measured on the LLFF fern)**, `NDCRules`: the field's x, y span the
  mean camera's image, so the grid follows the training image's width in pixels, not an object's size:
  one voxel every NDC_PIXELS_PER_VOXEL pixels of the image width, clamped to [NDC_MIN, NDC_MAX], start NDC_START; z'
  (inverse depth) needs far fewer steps than x, y have texels, so the march takes NDC_SAMPLES steps across z'
  in [-1, 1] whatever the grid, but no finer than NDC_MIN_STEP_VOXELS voxel (the occupancy grid's empty rule is an
  opacity per step: steps much finer than the grid empty every cell before the field has grown). NDC_RANK:
  TensoRF's LLFF components, most on the xy (image) plane. TV NDC_TV. Density through NDC_ACTIVATION (relu,
  TensoRF's LLFF setting) instead of the objects' softplus. The colour MLP stays DEFAULT_HIDDEN wide.
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
    """Forward-facing captures in NDC (module doc), measured on the LLFF fern; the measurements behind each constant
    are in docs/DENSITY_RULES.md ("NDC scenes")."""

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
