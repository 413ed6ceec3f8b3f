"""A run as the stages downstream see it: `load_trained(run_dir)` -> a `Run` that declares what it can do.

Every method's run (`model.methods`: the density field, the paper's NeRF, ...) and splats made from a run
(`model.splat_run`) are a `Run`: a scene (its cameras: refined ones for --refine-poses runs), an evaluation
background, a device, the image downscale it trained at, its pose-refinement record, its appearance codes, and a
set of capabilities (`CAPABILITIES`). A stage asks what a run can do (`can`, `require`) and says in one line when it
cannot; it never asks which method made the run. Each capability comes with its members:

- rays: `render_rays(rays_o [R, 3], rays_d [R, 3], *, infer=EXACT, median=True)` -> dict(rgb [R, 3], depth [R],
  depth_median [R], acc [R]) (t along the rays, scene frame);
- cameras: `render_camera(intr, world_from_cam, *, depth=True)` -> dict of numpy arrays (a rasteriser: splats);
- density: `density(x [N, 3])` -> sigma [N] (scene frame, per scene unit), `aabb` [2, 3], `occupancy` (a grid in the
  scene frame, or None), `density_function()` (the fastest query for large batches);
- sdf: `sdf(x [N, 3])` -> [N] signed distance (negative inside, scene units), `aabb` [2, 3];
- color: `color(x [N, 3], d [N, 3] or None)` -> rgb [N, 3];
- pose_opt: `render_differentiable(o, d, background)` -> dict(rgb, ...) with gradients to the rays, and
  `parameters()` (frozen while eval's test-pose optimisation moves a camera).

A run that is only weights plus a scene (no per-scene training) is a run like any other: its method's `load`
builds it from the files its config.json names.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import torch

from nerfpipe.data.confine import read_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Scene
from nerfpipe.model.device import resolve_device
from nerfpipe.model.methods.base import RunFiles
from nerfpipe.model.methods.registry import method_named, method_of_run

__all__ = ["CAPABILITIES", "Run", "can", "require", "require_any", "load_trained", "open_run_files"]

CAPABILITIES = {
    "rays": "render rays",
    "cameras": "render whole cameras",
    "density": "give a density at points",
    "sdf": "give a signed distance at points",
    "color": "give a colour at points",
    "pose_opt": "render differentiably (test-pose optimisation)",
}
"""Each capability and what it means, in the words of a stage's one-line refusal."""


@runtime_checkable
class Run(Protocol):
    """What every run gives the stages (module doc); the rest comes with its capabilities."""

    method: str
    """The method that made the run (for the manifests; stages never test it)."""
    capabilities: frozenset[str]
    scene: Scene
    background: torch.Tensor
    """[3] evaluation background."""
    device: torch.device
    downscale: float
    """The image downscale the run trained at (what render, depth, eval and splat default to)."""
    far: float
    """How far along its rays the run renders (scene units; inf: unbounded)."""
    pose_refinement: dict | None

    @property
    def appearance(self) -> Any:
        """Per-image appearance codes (`model.appearance.Appearance`), or None."""
        ...


def can(run: Any, capability: str) -> bool:
    """Whether `run` declares `capability`."""
    if capability not in CAPABILITIES:
        raise ValueError(f"unknown capability {capability!r}: expected one of {', '.join(CAPABILITIES)}")
    return capability in getattr(run, "capabilities", frozenset())


def _what_it_can(run: Any) -> str:
    caps = sorted(getattr(run, "capabilities", ()))
    return ", ".join(CAPABILITIES[c] for c in caps if c in CAPABILITIES) or "nothing a stage uses"


def require(run: Any, capability: str, *, stage: str) -> None:
    """UserError in one line when `run` cannot do what `stage` needs (`capability`)."""
    if not can(run, capability):
        raise UserError(
            f"{stage}: a {getattr(run, 'method', '?')} run cannot {CAPABILITIES[capability]}, which {stage} needs "
            f"(it can: {_what_it_can(run)})"
        )


def require_any(run: Any, capabilities: tuple[str, ...], *, stage: str) -> str:
    """The first of `capabilities` that `run` has; UserError in one line naming them all when it has none."""
    for capability in capabilities:
        if can(run, capability):
            return capability
    wanted = " or ".join(CAPABILITIES[c] for c in capabilities)
    raise UserError(
        f"{stage}: a {getattr(run, 'method', '?')} run cannot {wanted}, which {stage} needs "
        f"(it can: {_what_it_can(run)})"
    )


def open_run_files(run_dir: str | Path) -> RunFiles:
    """RUN_DIR's config.json, read; UserError when it is not a finished train run."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: run directory not found (not a train run directory)")
    if not (run_dir / "checkpoint.pt").is_file():
        raise UserError(f"{run_dir}: no checkpoint.pt (not a finished training run?)")
    cfg_path = run_dir / "config.json"
    if not cfg_path.is_file():
        raise UserError(f"{run_dir}: not a train run directory (no config.json)")
    doc = read_json(cfg_path)
    if not isinstance(doc, dict):
        raise UserError(f"{cfg_path}: expected a JSON object")
    return RunFiles(run_dir=run_dir, config=doc, config_path=cfg_path)


def load_trained(run_dir: str | Path, device: str | torch.device = "auto") -> Any:
    """RUN_DIR (config.json + checkpoint.pt), opened by the method its config.json names, on `device`."""
    files = open_run_files(run_dir)
    method = method_named(method_of_run(files.config, str(files.config_path)))
    return method.load(files, resolve_device(device))
