"""Trained X-ray runs: the attenuation field, its Beer-Lambert renderer, its checkpoint, and `load_xray_run`.

An X-ray run directory (`xray-train`): config.json, checkpoint.pt, metrics.csv, psnr_vs_time.png, volume.npy
(the reconstruction on the scene's grid, mu per length unit), manifest.json (last). The scene it was trained on
is named in config.json (`scene`) and read again with `data.projections.read_any`, always without
`trust_pickle`: a NAF pickle named there goes through the restricted unpickler (data.safe_pickle), so a run
whose config.json was edited to name a crafted pickle runs no code from it.

The field is `radiance.fields.TensoRF` with `has_color=False` (density only: mu(x) per length unit, no colour,
no view direction) in the scene's length units over the grid's box. Rendering is `radiance.render.
render_attenuation` (stratified samples between the ray's entry and exit of the box, or any sampler, e.g. the
occupancy marcher of `xray_marcher`; Beer-Lambert in the compositing core): optical_depth = -log(I / I0) =
sum mu_i delta_i.

    run = load_xray_run("runs/ct/run")                  # XrayRun
    mu = run.volume()                                   # [nx, ny, nz] on the scene grid (torch, CPU)
    drr = run.drr(angle=0.3)                            # [n_v, n_u] line integrals through the volume
    mip = run.mip(angle=0.3)                            # [n_v, n_u] maximum attenuation along each ray
    p = run.line_integrals(rays_o, rays_d)              # through the field itself (no voxelisation)
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import UserError
from nerfpipe.data.projections import ProjectionScene, read_any
from nerfpipe.data.rundir import find_run_scene
from nerfpipe.data.safe_pickle import PickleRefused
from nerfpipe.model.checkpoint import load_state
from nerfpipe.model.device import resolve_device
from nerfpipe.radiance.aabb import ray_aabb_segment
from nerfpipe.radiance.fields import Field, make_field
from nerfpipe.radiance.fields.voxel import VoxelField
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.render import Marcher, Sampler, StratifiedSampler, render_attenuation
from nerfpipe.radiance.space import Box
from nerfpipe.radiance.xray import VoxelGrid, XrayGeometry, detector_rays, siddon_project

__all__ = [
    "XRAY_CHECKPOINT_FORMAT",
    "XrayRun",
    "XRAY_FIELDS",
    "XrayField",
    "attenuation_field",
    "build_field",
    "grid_shape_at",
    "field_line_integrals",
    "xray_marcher",
    "field_volume",
    "load_xray_run",
    "read_xray_checkpoint",
    "save_xray_checkpoint",
    "samples_for",
]

XRAY_CHECKPOINT_FORMAT = "nerfpipe-xray-1"
MU_INIT_FRACTION = 0.5
"""The field starts at this fraction of `mu_ref` everywhere (softplus(shift) = 0.5)."""


def _voxel_field(grid: VoxelGrid, resolution: int, rank: int, mu_ref: float, init_std: float) -> Field:
    """mu = mu_ref * max(theta, 0) on a grid of `resolution` voxels along the longest axis."""
    shape = grid_shape_at(grid, resolution)
    return VoxelField(aabb=grid.box.tolist(), shape=shape, mu_scale=float(mu_ref), init=MU_INIT_FRACTION)


def _tensorf_field(grid: VoxelGrid, resolution: int, rank: int, mu_ref: float, init_std: float) -> Field:
    """TensoRF VM with `rank` components per axis, mu = mu_ref * softplus(f + shift)."""
    shift = math.log(math.expm1(MU_INIT_FRACTION))
    return make_field(
        {
            "kind": "fast",
            "aabb": grid.box.tolist(),
            "resolution": int(resolution),
            "density_rank": int(rank),
            "has_color": False,
            "view_dependent": False,
            "density_shift": shift,
            "density_scale": float(mu_ref),
            "init_std": init_std,
        }
    )


@dataclass(frozen=True)
class XrayField:
    """One attenuation field xray-train can fit: its name on the command line, the field kind its checkpoint records
    (`radiance.fields.FIELDS`), how a new one is made and how it is upsampled to `resolution` voxels along the
    grid's longest axis, and whether SART (linear in the unknowns) can fit it."""

    name: str
    recorded_as: str
    make: Callable[[VoxelGrid, int, int, float, float], Field]
    upsample: Callable[[Field, VoxelGrid, int], None]
    linear: bool


XRAY_FIELDS = {
    "grid": XrayField(
        name="grid",
        recorded_as="voxel",
        make=_voxel_field,
        upsample=lambda field, grid, res: field.upsample(grid_shape_at(grid, res)),
        linear=True,
    ),
    "tensorf": XrayField(
        name="tensorf",
        recorded_as="fast",
        make=_tensorf_field,
        upsample=lambda field, grid, res: field.upsample(res),
        linear=False,
    ),
}
"""The one table of X-ray fields: `xray-train --field NAME`."""


def attenuation_field(
    grid: VoxelGrid, *, kind: str, resolution: int, rank: int = 16, mu_ref: float, init_std: float = 0.1
) -> Field:
    """A density-only field over the grid's box, starting near MU_INIT_FRACTION * mu_ref everywhere
    (mu_ref: a typical attenuation, e.g. twice the scan's mean); `kind` one of `XRAY_FIELDS`."""
    if kind not in XRAY_FIELDS:
        raise ValueError(f"expected field kind one of {', '.join(XRAY_FIELDS)}, got {kind!r}")
    return XRAY_FIELDS[kind].make(grid, resolution, rank, mu_ref, init_std)


def grid_shape_at(grid: VoxelGrid, resolution: int) -> tuple[int, int, int]:
    """The grid's shape scaled so that its longest axis has `resolution` voxels (never above the grid's)."""
    longest = max(grid.shape)
    return tuple(max(1, min(n, round(n * resolution / longest))) for n in grid.shape)


def build_field(config: dict) -> Field:
    """Rebuild a field from `Field.config()` (`radiance.fields.make_field`)."""
    return make_field(config)


def samples_for(grid: VoxelGrid, step_ratio: float) -> int:
    """Samples per ray so that the longest chord (the box diagonal) is cut every `step_ratio` voxels."""
    diag = float(np.linalg.norm(np.asarray(grid.shape) * np.asarray(grid.spacing)))
    return max(2, int(math.ceil(diag / (step_ratio * min(grid.spacing)))))


def field_line_integrals(
    field: Field,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    box: Tensor,  # [2, 3]
    n_samples: int | None = None,
    *,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    sampler: Sampler | None = None,
) -> Tensor:
    """-log(I / I0) [R] through the field over each ray's chord of the box: n_samples stratified intervals
    (jittered from `generator` with `jitter`), or the samples of `sampler` instead (e.g. `xray_marcher`: only the
    occupied cells; a sampler jitters itself)."""
    if (n_samples is None) == (sampler is None):
        raise ValueError(f"expected one of n_samples and sampler, got {'neither' if sampler is None else 'both'}")
    if sampler is not None and (jitter or generator is not None):
        raise ValueError("expected jitter=False and generator=None with a sampler (the sampler jitters itself)")
    near, far = ray_aabb_segment(rays_o, rays_d, box, 0.0, float("inf"))
    if sampler is None:
        sampler = StratifiedSampler(n_samples=n_samples, jitter=jitter, generator=generator)
    out = render_attenuation(
        rays_o, rays_d, near=near, far=far, sampler=sampler, sigma_fn=lambda x, d: field.density(x)
    )
    return out["optical_depth"]


def xray_marcher(grid: OccupancyGrid, step_size: float) -> Marcher:
    """The occupancy marcher through the grid's box (the scene's, `field_line_integrals`' box) as a line-integral
    sampler: steps of step_size (length units) whose midpoints lie in occupied cells, from the occupied cells'
    box; `functools.partial(marcher, jitter=generator)` jitters it. What the cells marked empty hold (mu below
    the grid's threshold where `OccupancyGrid.update` looked) is left out of the line integrals, and a step whose
    midpoint is on the wrong side of an occupied cell's face moves up to a step of chord in or out."""
    aabb = tuple(tuple(float(v) for v in row) for row in grid.aabb.tolist())
    return Marcher(space=Box(aabb=aabb, near=0.0, far=math.inf), grid=grid, step_size=step_size)


@torch.no_grad()
def field_volume(field: Field, grid: VoxelGrid, chunk: int = 1 << 18) -> Tensor:
    """mu at every voxel centre of `grid`: [nx, ny, nz] float32 on the field's device."""
    x = grid.centers(dtype=torch.float32, device=field.device).reshape(-1, 3)
    out = torch.cat([field.density(x[i : i + chunk]) for i in range(0, x.shape[0], chunk)])
    return out.reshape(grid.shape)


def save_xray_checkpoint(path: Path, field: Field, opt: torch.optim.Optimizer | None, **state: Any) -> None:
    """checkpoint.pt: tensors and primitives only (loads with weights_only=True), written atomically."""
    doc = {
        "format": XRAY_CHECKPOINT_FORMAT,
        "field_config": field.config(),
        "field": field.state_dict(),
        "optimizer": opt.state_dict() if opt is not None else None,
        **state,
    }
    with atomic_path(path) as tmp:
        torch.save(doc, tmp)


def read_xray_checkpoint(path: Path, device: torch.device | str) -> dict:
    return load_state(
        path,
        device,
        fmt=XRAY_CHECKPOINT_FORMAT,
        missing="no checkpoint",
        kind=f"an X-ray run checkpoint ({XRAY_CHECKPOINT_FORMAT})",
    )


def load_field(state: dict, device: torch.device) -> Field:
    """Rebuild the field from a checkpoint dict (its resolution may have grown: upsampled grids)."""
    field = build_field(state["field_config"]).to(device)
    field.load_state_dict(state["field"])
    field.eval()
    return field


@dataclass
class XrayRun:
    """A trained X-ray run: the scene, the attenuation field and the renderers (no grad)."""

    run_dir: Path
    scene: ProjectionScene
    field: Field
    device: torch.device
    n_samples: int
    """Samples per ray for `line_integrals` (the run's inference step)."""

    @property
    def grid(self) -> VoxelGrid:
        return self.scene.grid

    @property
    def geometry(self) -> XrayGeometry:
        return self.scene.geometry

    def volume(self, grid: VoxelGrid | None = None) -> Tensor:
        """mu [nx, ny, nz] on `grid` (default: the scene's, i.e. the ground truth's voxels), CPU float32."""
        return field_volume(self.field, grid or self.grid).cpu()

    @torch.no_grad()
    def line_integrals(self, rays_o: Tensor, rays_d: Tensor, chunk: int = 4096) -> Tensor:
        """Line integrals [R] through the field itself (CPU float32)."""
        box = torch.as_tensor(self.grid.box, dtype=torch.float32, device=self.device)
        parts = [
            field_line_integrals(
                self.field,
                rays_o[i : i + chunk].to(self.device, torch.float32),
                rays_d[i : i + chunk].to(self.device, torch.float32),
                box,
                self.n_samples,
            ).cpu()
            for i in range(0, rays_o.shape[0], chunk)
        ]
        return torch.cat(parts) if parts else torch.zeros(0)

    def _view(self, angle: float, geometry: XrayGeometry | None) -> tuple[Tensor, Tensor, tuple[int, int]]:
        g = (geometry or self.geometry).with_angles([angle])
        o, d = detector_rays(g, 0, dtype=torch.float32)
        return o, d, g.detector_shape

    def drr(self, angle: float, geometry: XrayGeometry | None = None, volume: Tensor | None = None) -> Tensor:
        """Digitally reconstructed radiograph [n_v, n_u]: line integrals through the reconstructed volume
        (exact voxel projector); pass `volume` to reuse one already evaluated."""
        o, d, shape = self._view(angle, geometry)
        vol = self.volume() if volume is None else volume
        return siddon_project(vol, self.grid.spacing, self.grid.center, o, d).reshape(shape)

    def mip(self, angle: float, geometry: XrayGeometry | None = None, volume: Tensor | None = None) -> Tensor:
        """Maximum-intensity projection [n_v, n_u]: the largest mu along each ray."""
        o, d, shape = self._view(angle, geometry)
        vol = self.volume() if volume is None else volume
        return siddon_project(vol, self.grid.spacing, self.grid.center, o, d, reduce="max").reshape(shape)


def load_xray_run(run_dir: str | Path, device: str | torch.device = "auto") -> XrayRun:
    """Load an `xray-train` run directory; UserError when it is not one or its scene is gone."""
    run_dir = Path(run_dir)
    config_path = run_dir / "config.json"
    if not config_path.is_file():
        raise UserError(f"{run_dir}: not an X-ray run (no config.json)")
    try:
        config = json.loads(config_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{config_path}: not valid JSON ({exc})") from None
    if not isinstance(config, dict) or "scene" not in config:
        raise UserError(f"{config_path}: not an X-ray run config (no 'scene')")
    dev = resolve_device(device)
    state = read_xray_checkpoint(run_dir / "checkpoint.pt", dev)
    tried = find_run_scene(run_dir, config, ("scene", "scene_abs"))
    scene_path = next((p for p in tried if p.exists()), tried[-1])
    try:
        scene = read_any(scene_path)  # never trust_pickle: this path comes from the run, not from the user
    except PickleRefused as exc:
        raise UserError(
            f"{exc} (the scene named in {config_path}; a run's scene is never unpickled with trust)"
        ) from None
    return XrayRun(
        run_dir=run_dir,
        scene=scene,
        field=load_field(state, dev),
        device=dev,
        n_samples=int(state.get("n_samples_render", samples_for(scene.grid, 0.5))),
    )
