"""train's `Config`: the run's options, the method's (`options`: its `Method.Options`, `model.methods`) and pose
refinement's (`RefineOptions`) in groups of their own, and `validate`, every check that needs the config alone
(run calls it before anything is read).

A field that may be None is an automatic default: `stages.train.defaults.resolve_defaults` replaces each None by
the value the scene and the device call for (with its reason in the manifest), and config.json records that
resolved Config (`stages.train.setup`); the method's options resolve the same way (`Method.prepare`). The command
line spells the groups flat (`--resolution`, `--refine-poses`, `--camera-lr`: `cli.GROUPS`; every method's options:
`cli.METHOD_GROUPS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from nerfpipe.data.errors import UserError
from nerfpipe.model.methods.registry import DEFAULT, method_named
from nerfpipe.radiance.space import SPACES

__all__ = ["Config", "RefineOptions", "validate", "method_options"]

BACKGROUNDS = ("auto", "black", "white", "random", "learned")


@dataclass(frozen=True, kw_only=True)
class RefineOptions:
    """Pose refinement's options (`Config.refine`)."""

    focal: bool = False
    """With refine_poses: also refine one focal-length scale shared by every camera."""
    camera_lr: float = 1e-2
    """refine_poses: the corrections' learning rate (radians and scene units per step, Adam), reached after
    the warm-up and decayed like the field's (docs/MEASUREMENTS.md, "Pose refinement")."""


@dataclass(frozen=True, kw_only=True)
class Config:
    scene_dir: Path
    """Folder with transforms.json (or the file itself)."""
    run_dir: Path
    """Output run directory (created)."""
    method: str = DEFAULT
    """The method to train (`model.methods`): density (TensoRF-style field, the default), nerf (the paper's MLPs),
    or another registered one; its options are spelt flat on the command line (`--resolution`, `--tv`, ...)."""
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
    """Rays per optimizer step (None: the method's, else 1024 on CPU, 8192 on CUDA; stages.train.defaults)."""
    lr: float | None = None
    """Base learning rate (None: the method's: 0.03 for the density field's grids (its MLP at lr/20), 5e-4 for
    nerf)."""
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
    options: Any = None
    """The method's options group (its `Method.Options`; None: its defaults), on the command line its own flags."""
    final_eval_views: int | None = None
    """Test views scored in full at the end, evenly spaced over the test split (the NeRF Blender test views follow
    a path: the first k views are one arc). None: every test view, on every stride-th pixel, the stride that fits
    `final_eval_fraction` of max_seconds at the measured render speed (`defaults.final_eval_stride`)."""
    downscale: float | None = None
    """Train and evaluate on images shrunk by this factor (area filter). None: the smallest power of two that
    brings the long side to <= 800 px on CPU, <= 1600 px on CUDA (nerfstudio's auto downscale; a phone's
    1080x1920 trains at 270x480 on CPU, where the grid could not use more pixels in the time)."""
    final_eval_fraction: float = 0.1
    """Budget of the end-of-run PSNR, as a fraction of max_seconds (when final_eval_views is None)."""
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
    method_options(config)
    if config.refine is not None and not config.refine.camera_lr > 0:
        raise UserError(f"expected camera_lr > 0, got {config.refine.camera_lr}")


def _choices(config: Config) -> None:
    method_named(config.method)  # UserError naming the methods there are
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


def method_options(config: Config) -> Any:
    """The method's options: `config.options`, or the method's defaults when None; checked by the method
    (UserError naming the option). A group of another method's options is refused."""
    method = method_named(config.method)
    options = method.Options() if config.options is None else config.options
    if not isinstance(options, method.Options):
        raise UserError(
            f"options: expected the {method.name} method's options ({method.Options.__name__}), "
            f"got {type(options).__name__}"
        )
    method.validate(options)
    return options
