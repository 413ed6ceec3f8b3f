"""Stage `xray-simulate`: Beer-Lambert projections of a CT volume -> a projection scene.

    nerfpipe xray-simulate VOLUME OUT_DIR [--mode cone|parallel] [--views 50] [--arc 180] [--detector NV,NU]
        [--noise I0] [--voxel-size 2.0] [--dso 1000] [--dsd 1500] [--test-views 10]

VOLUME: `.npy`, `.mat` (one 3-D variable, or `--key`), `.raw` (`--shape`, `--dtype`), `.nii`/`.nii.gz`
(data.volumes). Attenuation mu per mm; the voxel size comes from NIfTI headers, else `--voxel-size` (mm).

Geometry (radiance.xray's frame): the volume is centred on the rotation axis (+z). Training views are `views`
angles evenly spaced over `arc` degrees from `start_angle` (NAF's `*_50` sets: cone beam, 50 views over 180
degrees); held-out test views are `test_views` angles spread over the full circle, half a step off the
training angles. The default detector has pixels of one voxel at the isocentre and covers the volume's shadow
from every angle (radiance.xray.shadow_detector); `--detector NV,NU` fixes the pixel counts (same coverage).

Projector: radiance.xray.siddon_project, exact line integrals through the box-voxel volume (float32; see the
docs/XRAY.md for its accuracy against float64 and analytic chords). `--noise I0`: Poisson counts with I0 photons per
unobstructed pixel, turned back into line integrals by radiance.xray.line_integral_from_counts (0 counts ->
half a photon; counts above I0 give negative line integrals, kept). Test views stay noise-free (a reference).

Writes OUT_DIR/projections.npy, volume.npy (the ground truth), projections.json and manifest.json (last).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.projections import ProjectionScene, validate_geometry, write_projection_scene
from nerfpipe.data.rundir import config_to_json, output_folder, write_manifest
from nerfpipe.data.volumes import read_volume
from nerfpipe.model.device import cpu_threads
from nerfpipe.radiance.xray import (
    VoxelGrid,
    XrayGeometry,
    line_integral_from_counts,
    poisson_counts,
    project_views,
    shadow_detector,
)

__all__ = ["Config", "Outputs", "run", "make_geometry"]

VERSION = "1"


@dataclass(frozen=True, kw_only=True)
class Config:
    volume: Path
    """CT volume: .npy, .mat, .raw (with --shape and --dtype) or .nii/.nii.gz; attenuation per mm."""
    out_dir: Path
    """Output scene folder (projections.json, projections.npy, volume.npy, manifest.json)."""
    mode: Literal["cone", "parallel"] = "cone"
    """Beam: cone (a point source) or parallel."""
    views: int = 50
    """Training views, evenly spaced over the arc."""
    arc: float = 180.0
    """Arc covered by the training views, degrees (360: a full circle)."""
    start_angle: float = 0.0
    """Angle of the first view, degrees."""
    test_views: int = 10
    """Held-out views (noise-free), spread over the full circle half a step off the training angles."""
    detector: tuple[int, int] | None = None
    """Detector pixels (rows, columns); None: pixels of one voxel at the isocentre, covering the volume."""
    dso: float = 1000.0
    """Source to rotation axis, mm."""
    dsd: float = 1500.0
    """Source to detector, mm."""
    noise: float | None = None
    """Poisson noise: photons per unobstructed detector pixel (I0), e.g. 1e5; None: noise-free."""
    voxel_size: float = 2.0
    """Voxel size in mm for formats that carry none (.npy, .mat, .raw)."""
    key: str | None = None
    """.mat: the variable to read (default: the only 3-D one)."""
    shape: tuple[int, int, int] | None = None
    """.raw: volume shape NX,NY,NZ (x fastest on disk)."""
    dtype: str | None = None
    """.raw: numpy dtype, e.g. float32, uint16."""
    seed: int = 0
    """Seed for the noise."""
    threads: int | None = None
    """torch intra-op threads (None: torch's default)."""
    overwrite: bool = False
    """Replace an earlier output in out_dir (set aside in OUT_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    scene: Path
    """projections.json."""
    manifest: Path
    n_views: int
    detector: tuple[int, int]
    max_line_integral: float
    seconds: float


def make_geometry(config: Config, grid: VoxelGrid) -> tuple[XrayGeometry, tuple[int, ...], tuple[int, ...]]:
    """The scan: geometry with training then test angles, and the two index lists."""
    if config.views < 1:
        raise UserError(f"views: expected >= 1, got {config.views}")
    if config.test_views < 0:
        raise UserError(f"test_views: expected >= 0, got {config.test_views}")
    if not (0 < config.arc <= 360):
        raise UserError(f"arc: expected 0 < arc <= 360 degrees, got {config.arc}")
    probe = validate_geometry(
        XrayGeometry(mode=config.mode, dso=config.dso, dsd=config.dsd, detector_shape=(1, 1), detector_pitch=(1.0, 1.0))
    )
    voxel = min(grid.spacing)
    pitch = voxel * probe.magnification
    try:
        shape, pitches = shadow_detector(grid.box, config.mode, probe.dso, probe.dsd, pitch)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if config.detector is not None:
        nv, nu = config.detector
        if nv < 1 or nu < 1:
            raise UserError(f"detector: expected positive pixel counts, got {config.detector}")
        size = max(shape[0] * pitch, shape[1] * pitch)  # square field of view covering the shadow
        pitches = (size / nv, size / nu)
        shape = (nv, nu)
    start = math.radians(config.start_angle)
    step = math.radians(config.arc) / config.views
    train = [start + i * step for i in range(config.views)]
    test_step = 2 * math.pi / max(config.test_views, 1)
    test = [start + (i + 0.5) * test_step + step / 2 for i in range(config.test_views)]
    geometry = XrayGeometry(
        mode=config.mode,
        dso=probe.dso,
        dsd=probe.dsd,
        detector_shape=shape,
        detector_pitch=pitches,
        angles=tuple(train + test),
        length_unit="mm",
    )
    n = config.views
    return geometry, tuple(range(n)), tuple(range(n, n + config.test_views))


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """See the module doc; torch's CPU threads are set to config.threads for the call and restored after."""
    with output_folder(config.out_dir, overwrite=config.overwrite):
        with cpu_threads(config.threads):
            return _run(config, progress)


def _run(config: Config, progress: Progress | None) -> Outputs:
    started = time.time()
    progress = progress or NO_PROGRESS
    if config.noise is not None and not (math.isfinite(config.noise) and config.noise > 0):
        raise UserError(f"noise: expected a photon count I0 > 0, got {config.noise}")
    vol = read_volume(config.volume, spacing=config.voxel_size, key=config.key, shape=config.shape, dtype=config.dtype)
    grid = VoxelGrid(shape=tuple(vol.data.shape), spacing=vol.spacing)
    geometry, train, test = make_geometry(config, grid)

    t0 = time.perf_counter()
    volume_t = torch.from_numpy(vol.data)
    task = progress.add_task("projecting", total=geometry.n_views)
    views = []
    for v in range(geometry.n_views):
        views.append(project_views(volume_t, grid.spacing, grid.center, geometry.subset([v]))[0])
        progress.advance(task)
    clean = torch.stack(views)  # [V, n_v, n_u] float32
    projector_seconds = time.perf_counter() - t0

    noise = None
    proj = clean.clone()
    if config.noise is not None:
        gen = torch.Generator().manual_seed(config.seed)
        counts = poisson_counts(clean[list(train)], config.noise, gen)
        proj[list(train)] = line_integral_from_counts(counts, config.noise).to(proj.dtype)
        noise = {
            "model": "poisson",
            "i0": config.noise,
            "views": "train",
            "starved_pixels": int((counts == 0).sum()),
            "above_i0_pixels": int((counts > config.noise).sum()),
            "starved_rule": "0 counts -> half a photon: p = log(2 I0)",
        }

    scene = ProjectionScene(
        geometry=geometry,
        projections=proj.numpy(),
        splits={"train": train, "test": test},
        grid=grid,
        volume=vol.data,
        noise=noise,
        extra={"source": {"stage": "xray-simulate", "volume": str(config.volume), **vol.note}},
    )
    out_dir = Path(config.out_dir)
    scene_json = write_projection_scene(scene, out_dir)
    manifest = write_manifest(
        out_dir,
        stage="xray-simulate",
        started=started,
        version=VERSION,
        config=config_to_json(config),
        inputs=[config.volume],
        outputs=[out_dir / "projections.npy", out_dir / "volume.npy", scene_json],
        used={
            "projector": "radiance.xray.siddon_project (exact box-voxel line integrals, float32)",
            "projector_seconds": round(projector_seconds, 2),
            "rays": int(geometry.n_views * np.prod(geometry.detector_shape)),
            "geometry": {
                "mode": geometry.mode,
                "dso": geometry.dso,
                "dsd": geometry.dsd,
                "detector_shape": list(geometry.detector_shape),
                "detector_pitch": list(geometry.detector_pitch),
            },
            "voxel_size_mm": list(vol.spacing),
            "noise": noise,
        },
        left_out={"scatter, beam hardening, detector blur": "monochromatic, ideal detector: Beer-Lambert only"},
    )
    return Outputs(
        out_dir=out_dir,
        scene=scene_json,
        manifest=manifest,
        n_views=len(train),
        detector=tuple(geometry.detector_shape),
        max_line_integral=float(clean.max()),
        seconds=time.time() - started,
    )
