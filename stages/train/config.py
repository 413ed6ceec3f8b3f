"""train's `Config`: the run's options, the fast field's (`FastOptions`) and pose refinement's (`RefineOptions`) in
groups of their own, and `validate`, every check that needs the config alone (run calls it before anything is
read).

A field that may be None is an automatic default: `stages.train.defaults.resolve_defaults` replaces each None by
the value the scene and the device call for (with its reason in the manifest), and config.json records that
resolved Config (`stages.train.setup`). The command line spells the groups flat (`--resolution`,
`--refine-poses`, `--camera-lr`: `cli.GROUPS`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from nerfpipe.data.errors import UserError
from nerfpipe.radiance.fields.fast import DENSITY_ACTIVATIONS, split_rank
from nerfpipe.radiance.space import SPACES

__all__ = ["Config", "FastOptions", "RefineOptions", "validate"]

BACKGROUNDS = ("auto", "black", "white", "random", "learned")


@dataclass(frozen=True, kw_only=True)
class FastOptions:
    """The `fast` field's grid, march and priors (TensoRF VM + occupancy grid); the vanilla field reads only the
    resolved grid size and step (its render settings), none of the priors."""

    resolution: tuple[int, int] | None = None
    """fast: grid resolution per axis at the start and at the end (coarse-to-fine upsampling). None: the scene
    kind's rule (stages.train.rules.RULES): objects and contracted scenes from the object's size in pixels
    (lego_100 -> 64,160, lego_400 -> 96,300), forward-facing (NDC) scenes from the image's width."""
    rank: tuple[int, ...] | None = None
    """fast: the VM field's components per plane (`radiance.fields.fast.TensoRF`): density and appearance, alike on
    every plane (2 counts), or each plane's own (6: density on the xy, xz, yz planes, then appearance). None: the
    scene kind's rule (stages.train.rules.RULES): TensoRF's 16,48 for objects and contracted scenes, TensoRF's
    LLFF 16,4,4,48,12,12 for forward-facing (NDC) scenes (the xy plane is the image plane)."""
    upsample_at: tuple[float, ...] | None = None
    """fast: run-progress fractions at which the grid is upsampled (geometric steps to the final size). None:
    0.05,0.1,0.2,0.3; with refine_poses 0.2,0.3,0.4,0.5 (coarse-to-fine, `stages.train.defaults`)."""
    step_ratio: float | None = None
    """fast: marching step in voxels of the final grid (None: the scene kind's rule: objects 2 below a 200 grid,
    else 1; contracted 2 on CPU; NDC a fixed number of steps across inverse depth)."""
    render_step_factor: float = 0.5
    """fast: evaluation and rendering march at this fraction of the training step. The field is continuous, so
    finer quadrature at inference only costs render time: lego_100 after 120 s (trained at 2 voxels) 31.94 ->
    32.43 dB at 0.5 (0.25: 32.46 dB), lego_400 after 900 s (trained at 1 voxel) +0.15 dB; rays/s about halve."""
    occupancy_resolution: int = 64
    """fast: occupancy grid cells per axis."""
    occupancy_every: int = 16
    """fast: update the occupancy grid every this many steps."""
    density_l1: float = 0.0
    """fast: weight of the L1 sparsity prior on the density factors."""
    tv: float | None = None
    """fast: weight of TensoRF's total-variation prior on the field's planes (`TensoRF.tv`; TensoRF's LLFF setting
    is 0.01). None: the scene kind's rule (stages.train.rules.RULES): 0.01 for contracted scenes (real captures,
    where a VM field otherwise paints streaks and floaters into sparsely seen space: fox held-out 13.7 -> 17.8 dB),
    NDC's own measured weight, 0 for box scenes (objects)."""
    density_activation: Literal["softplus", "relu"] | None = None
    """fast: the field's density activation (`radiance.fields.fast.TensoRF`): softplus (shift -10) or relu. None:
    the scene kind's rule (stages.train.rules.RULES): relu for forward-facing (NDC) scenes, TensoRF's LLFF setting
    (fern: +1.3 dB at 2,000 steps), softplus for objects and contracted scenes."""
    mlp_width: int | None = None
    """fast: width of the colour MLP's two hidden layers (`radiance.fields.fast.TensoRF`'s hidden). None: the scene
    kind's rule (stages.train.rules.RULES): 64 for every kind (`radiance.fields.fast.DEFAULT_HIDDEN`); TensoRF's LLFF
    128 gave the fern +0.1 dB at 27 % fewer rays a second when rendering."""
    depth_loss: float | None = None
    """fast, contracted scenes: weight of DS-NeRF's depth loss on rays through the sparse points each training
    photo observed (transforms.json's `sparse_depth_path`, written by `convert` from COLMAP; data.sparse_depth).
    None: `stages.train.defaults.DEPTH_LOSS` when the scene has them and is contracted, else 0 (and the manifest
    says why)."""
    distortion: float = 0.0
    """fast, contracted scenes: weight of mip-NeRF 360's distortion loss (its lambda is 0.01), which pulls each
    ray's weight into one compact peak (radiance.regularizers). Off by default: on the fox (300 s budget, CPU) it
    left held-out PSNR where it was (13.2 dB at 150 s with 0.01 and without): the field there is undertrained
    (0.3 epochs), not foggy by choice."""


@dataclass(frozen=True, kw_only=True)
class RefineOptions:
    """Pose refinement's options (`Config.refine`)."""

    focal: bool = False
    """With refine_poses: also refine one focal-length scale shared by every camera."""
    camera_lr: float = 1e-2
    """refine_poses: the corrections' learning rate (radians and scene units per step, Adam), reached after
    the warm-up and decayed like the field's. 48 px scene, 3 deg / 3 % perturbations, 1000 steps with the
    coarse-to-fine grid: median rotation error 3.02 -> 0.67 deg at 5e-3, -> 0.55 deg at 1e-2 (2e-2 without
    coarse-to-fine drifted to 20 deg)."""


@dataclass(frozen=True, kw_only=True)
class Config:
    scene_dir: Path
    """Folder with transforms.json (or the file itself)."""
    run_dir: Path
    """Output run directory (created)."""
    field: Literal["fast", "vanilla"] = "fast"
    """Field: "fast" (TensoRF VM + occupancy grid, the default) or "vanilla" (the NeRF paper's MLP)."""
    max_steps: int = 30000
    """Stop after this many optimizer steps (counted across resumes)."""
    max_seconds: float = 900.0
    """Stop after this many seconds of training (counted across resumes, periodic evaluation excluded)."""
    device: str = "auto"
    """torch device: auto (CUDA when available, else CPU), cpu, cuda, cuda:N."""
    seed: int = 0
    """Seed for initialisation and ray batches."""
    resume: bool = False
    """Continue from run_dir/checkpoint.pt (step count, optimizer state and elapsed time continue)."""
    overwrite: bool = False
    """Replace the run already in run_dir (set aside in RUN_DIR.previous/ until this run succeeds); without it,
    or --resume, train refuses a folder that holds a run."""
    batch_rays: int | None = None
    """Rays per optimizer step (None: 1024 on CPU, 8192 on CUDA; stages.train.defaults)."""
    lr: float | None = None
    """Base learning rate (None: 0.03 for fast grids (MLP at lr/20), 5e-4 for vanilla).
    Fast, lego_100, 120 s: 0.02 -> 31.0 dB, 0.03 -> 31.5 dB, 0.05 -> 31.1 dB (single runs, 2 idle CPU cores)."""
    lr_decay: float = 0.1
    """Final learning-rate factor reached at the end of the run (exponential decay)."""
    eval_every: int = 250
    """Evaluate test PSNR on `eval_pixels` held-out pixels every this many steps (0: only at the end)."""
    eval_pixels: int = 4096
    """Held-out pixels used for the periodic test PSNR (full test images are rendered at the end)."""
    log_every: int = 25
    """Write a metrics row every this many steps."""
    checkpoint_every: int = 1000
    """Write checkpoint.pt every this many steps (and at the end, and on Ctrl-C or SIGTERM)."""
    checkpoint_seconds: float = 60.0
    """Also write checkpoint.pt every this many seconds of wall-clock time, so a killed run loses at most that
    (0: off)."""
    scene_model: Literal["auto", "box", "ndc", "contract"] = "auto"
    """Where the field lives: auto, box, ndc or contract. box: the scene's aabb (objects on a plain or
    transparent background). ndc: normalised device coordinates of the mean camera (forward-facing captures;
    NeRF's LLFF mode, `radiance.ndc`). contract: the scene's box at full resolution and all space beyond it
    contracted into a shell (mip-NeRF 360 / nerfacto; `radiance.contraction`): captures that see a room or a
    landscape. auto: ndc when forward-facing, box with alpha or a plain background, contract otherwise."""
    background: Literal["auto", "black", "white", "random", "learned"] = "auto"
    """What empty space shows: auto, black, white, random or learned. auto: random per ray for images with
    alpha (white at evaluation), the border colour when >= 90 % of the views' border pixels are one colour
    (tiny-NeRF's black, renders on white), a learned colour otherwise (`stages.train.defaults`)."""
    view_dependent: bool | None = None
    """Colour depends on view direction (None: on for every scene; off suits Lambertian scenes)."""
    fast: FastOptions = dataclasses.field(default_factory=FastOptions)
    """The fast field's grid, march and priors (on the command line: `--resolution`, `--tv`, ...)."""
    final_eval_views: int | None = None
    """Test views rendered in full at the end, evenly spaced over the test split (None: as many as fit in
    `final_eval_fraction` of max_seconds at the measured render speed, at least 1; `eval` scores them all).
    Evenly spaced: the NeRF Blender test views follow a path, so the first k views are one arc."""
    downscale: float | None = None
    """Train and evaluate on images shrunk by this factor (area filter). None: the smallest power of two that
    brings the long side to <= 800 px on CPU, <= 1600 px on CUDA (nerfstudio's auto downscale; a phone's
    1080x1920 trains at 270x480 on CPU, where the grid could not use more pixels in the time)."""
    final_eval_fraction: float = 0.1
    """Budget of the final full-image evaluation, as a fraction of max_seconds (when final_eval_views is None)."""
    threads: int | None = None
    """CPU: torch intra-op threads during the run (None: torch's default). On a shared or oversubscribed CPU,
    1 can be many times faster than 2 (measured 0.16 s vs 2.0 s per step on the 2-core dev machine)."""
    refine: RefineOptions | None = None
    """Refine the training cameras jointly with the field (NeRF--): a per-camera SE(3) correction with its own
    Adam, learning rate and warm-up (`model.camera_opt`). The refined cameras are saved in the run (render,
    depth, mesh and eval use them; test views are mapped into the refined frame by a similarity) and written
    to RUN_DIR/transforms.json; the manifest lists each camera's correction. None: off, the input cameras are
    taken as exact (on the command line: `--refine-poses`, `--refine-focal`, `--camera-lr`)."""
    appearance: bool = False
    """Learn a small appearance code per training image (NeRF-W) that changes colour only (exposure, white
    balance, colour cast; density is shared); novel views render with the mean code (`model.appearance`)."""


def validate(config: Config) -> None:
    """Every check the config alone allows (UserError naming the field), before any file is read."""
    _choices(config)
    _budget(config)
    _fast(config.fast)
    if config.refine is not None and not config.refine.camera_lr > 0:
        raise UserError(f"expected camera_lr > 0, got {config.refine.camera_lr}")


def _choices(config: Config) -> None:
    if config.field not in ("fast", "vanilla"):
        raise UserError(f"unknown field {config.field!r}: expected fast or vanilla")
    if config.scene_model != "auto" and config.scene_model not in SPACES:
        raise UserError(f"unknown scene model {config.scene_model!r}: expected auto, {', '.join(SPACES)}")
    if config.background not in BACKGROUNDS:
        raise UserError(f"unknown background {config.background!r}: expected auto, black, white, random or learned")
    if config.resume and config.overwrite:
        raise UserError("pass either --resume (continue the run) or --overwrite (replace it), not both")


def _budget(config: Config) -> None:
    """Steps, time, batches, learning rate, logging, checkpoints, evaluation, images and threads."""
    if config.max_steps < 0 or not config.max_seconds > 0:
        raise UserError(f"expected max_steps >= 0 and max_seconds > 0, got {config.max_steps}, {config.max_seconds}")
    if config.batch_rays is not None and config.batch_rays < 1:
        raise UserError(f"expected batch_rays >= 1, got {config.batch_rays}")
    if config.lr is not None and not config.lr > 0:
        raise UserError(f"expected lr > 0, got {config.lr}")
    if config.log_every < 1 or config.eval_every < 0 or config.eval_pixels < 1:
        raise UserError(
            f"expected log_every >= 1, eval_every >= 0 and eval_pixels >= 1, got {config.log_every}, "
            f"{config.eval_every}, {config.eval_pixels}"
        )
    if config.checkpoint_every < 1 or not config.checkpoint_seconds >= 0:
        raise UserError(
            f"expected checkpoint_every >= 1 and checkpoint_seconds >= 0, got "
            f"{config.checkpoint_every}, {config.checkpoint_seconds}"
        )
    if config.threads is not None and config.threads < 1:
        raise UserError(f"expected threads >= 1, got {config.threads}")
    if config.downscale is not None and not config.downscale >= 1:
        raise UserError(f"expected downscale >= 1, got {config.downscale}")
    if config.final_eval_views is not None and config.final_eval_views < 1:
        raise UserError(f"expected final_eval_views >= 1, got {config.final_eval_views}")
    if not (config.final_eval_fraction > 0):
        raise UserError(f"expected final_eval_fraction > 0, got {config.final_eval_fraction}")


def _fast(fast: FastOptions) -> None:
    """The fast field's grid, march and prior weights."""
    if fast.resolution is not None and (len(fast.resolution) != 2 or min(fast.resolution) < 2):
        raise UserError(f"expected resolution (start, end) >= 2, got {fast.resolution}")
    if fast.density_activation is not None and fast.density_activation not in DENSITY_ACTIVATIONS:
        raise UserError(
            f"unknown density activation {fast.density_activation!r}: expected one of {', '.join(DENSITY_ACTIVATIONS)}"
        )
    if fast.mlp_width is not None and fast.mlp_width < 1:
        raise UserError(f"--mlp-width: expected >= 1, got {fast.mlp_width}")
    if fast.rank is not None:
        try:
            split_rank(fast.rank)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    at = fast.upsample_at
    if at is not None and (any(not 0 <= a <= 1 for a in at) or list(at) != sorted(at)):
        raise UserError(f"expected upsample_at: increasing fractions in [0, 1], got {at}")
    if not ((fast.step_ratio is None or fast.step_ratio > 0) and 0 < fast.render_step_factor <= 1):
        raise UserError(
            f"expected step_ratio > 0 and 0 < render_step_factor <= 1, got {fast.step_ratio}, {fast.render_step_factor}"
        )
    if fast.occupancy_resolution < 1 or fast.occupancy_every < 1:
        raise UserError(
            f"expected occupancy_resolution >= 1 and occupancy_every >= 1, got "
            f"{fast.occupancy_resolution}, {fast.occupancy_every}"
        )
    if not fast.distortion >= 0:
        raise UserError(f"expected distortion >= 0, got {fast.distortion}")
    if fast.tv is not None and not fast.tv >= 0:
        raise UserError(f"--tv: expected >= 0, got {fast.tv}")
    if fast.depth_loss is not None and not fast.depth_loss >= 0:
        raise UserError(f"--depth-loss: expected >= 0, got {fast.depth_loss}")
    if not fast.density_l1 >= 0:
        raise UserError(f"expected density_l1 >= 0, got {fast.density_l1}")
