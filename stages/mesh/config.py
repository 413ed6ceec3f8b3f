"""The `mesh` stage's Config and Outputs, the CLI's parsers for its options, and the Config's validation."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from nerfpipe.data.errors import UserError
from nerfpipe.data.export_frame import check_frame_options
from nerfpipe.stages.mesh.cleanup import Cleanup
from nerfpipe.stages.mesh.texture_views import TEXTURE_VIEWS

__all__ = ["Config", "Outputs", "FORMATS", "FORMAT_NAMES", "parse_threshold", "parse_bbox", "validate"]

FORMATS = (".ply", ".obj", ".glb")
FORMAT_NAMES = {".ply": "ply", ".obj": "obj", ".glb": "gltf"}
"""Extension -> the `data.export_frame.FORMAT_UP` key whose up axis the upright frame takes."""


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory (config.json + checkpoint.pt from `train`)."""
    out: Path
    """Output mesh; the format follows the extension: .ply, .obj or .glb. OUT.report.json goes next to it."""
    method: Literal["density", "poisson"] = "density"
    """Surface extraction: "density" marching cubes on the density at the iso-level (steps 2-4); "poisson" screened
    Poisson on the points where training rays end, with density normals (`stages.mesh.poisson`, its defaults)."""
    resolution: int = 256
    """Voxels along the longest side of the box (cubic voxels)."""
    threshold: float | Literal["auto", "global"] = "auto"
    """Iso-level on density (per scene-frame unit), "auto" (levels by region: the densities where training rays
    become half opaque near each point) or "global" (their median, one level for the whole scene)."""
    bbox: tuple[float, float, float, float, float, float] | None = None
    """Box to mesh, (x0, y0, z0, x1, y1, z1) in the frame chosen by `frame`; None: the box `crop` finds."""
    crop: Literal["auto", "looked-at", "occupied", "field"] = "auto"
    """Without a bbox, what to mesh: "looked-at" the box of what the training views' central rays hit, the
    support plane (a wall, floor, table) cut away (`stages.mesh.crop`); "occupied" the occupancy grid's occupied
    cells; "field" the field's whole (inner) box; "auto": occupied for object scenes (alpha or plain background),
    looked-at for real captures."""
    frame: Literal["upright", "user", "normalized"] = "upright"
    """Output (and bbox) frame: "upright" = the user's frame turned so that the scene's up is the format's up (+Y for
    .glb and .obj, +Z for .ply), the scene's centre at the origin (`data.export_frame`); "user" = the source frame
    before convert, as it came in (e.g. COLMAP's); "normalized" = the scene frame the field was trained in."""
    up: tuple[float, float, float] | None = None
    """With frame "upright": the scene's up as a direction x,y,z in the user's frame; None: the scene frame's +z
    (convert's choice: the cameras' mean up for COLMAP and LLFF worlds)."""
    target_faces: int = 300_000
    """Decimate to at most this many faces (quadric edge collapse); 0: keep all."""
    cleanup: Cleanup | None = field(default_factory=Cleanup)
    """Cleanup steps (None: the raw marching-cubes mesh, `--no-cleanup`)."""
    colors: bool = True
    """Write per-vertex colours from the field (ignored for density-only fields)."""
    texture: bool = False
    """Bake a texture from the field instead of vertex colours (`stages.mesh.texture`): OUT.obj writes OUT.obj,
    OUT.mtl and OUT.png; OUT.glb embeds the PNG. Not for .ply."""
    texture_size: int | None = None
    """Texture width = height in texels (a power of two); None: from the face count (256..2048)."""
    texture_views: int = TEXTURE_VIEWS
    """Training cameras whose photos (or renders) colour the texels they see (`stages.mesh.texture_views`); 0: every
    texel coloured by the field along its normal only."""
    texture_source: Literal["photos", "field"] = "photos"
    """What the cameras show the texels: "photos" the training photos (the colours as they were captured), "field"
    the field's renders of those cameras; the photos fall back to the renders where they cannot be read."""
    close_gaps: int = 3
    """Before marching cubes, close the sampled volume along each axis over this many voxels (`stages.mesh.surface.
    close_gaps`): fills gaps up to 2 voxels thin, the planes of ~0 density a grid field's line factors leave (they cut
    `make demo`'s objects into 12 slices), and also real grooves that thin; 1: off."""
    coarse_resolution: int = 128
    """Coarse pass: the fine grid is evaluated only in blocks near the surface of a grid about this fine
    (>= resolution: every voxel is evaluated)."""
    threshold_rays: int = 8192
    """Training-view rays marched for the level and for the self-check's comparison with the field."""
    device: str = "auto"
    """Torch device for the field ("auto": CUDA when available)."""
    chunk: int = 1 << 18
    """Points per field query (memory vs speed)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    mesh: Path
    """The mesh file."""
    report: Path
    """OUT.report.json next to the mesh (written last)."""
    vertices: int
    faces: int
    threshold: float | None
    """The iso-level used (density per scene-frame unit; with levels by region, their median over the training
    rays); None for method poisson."""
    watertight: bool
    seconds: float


def parse_threshold(text: str) -> float | Literal["auto", "global"]:
    """'auto', 'global' or a finite number (for the CLI)."""
    if text.strip().lower() in ("auto", "global"):
        return text.strip().lower()  # type: ignore[return-value]
    try:
        value = float(text)
    except ValueError:
        raise UserError(f"--threshold: expected 'auto', 'global' or a number, got {text!r}") from None
    if not math.isfinite(value):
        raise UserError(f"--threshold: expected a finite number, got {text!r}")
    return value


def parse_bbox(text: str) -> tuple[float, float, float, float, float, float] | None:
    """'auto' or 'x0,y0,z0,x1,y1,z1' (for the CLI)."""
    if text.strip().lower() == "auto":
        return None
    try:
        vals = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise UserError(f"--bbox: expected 'auto' or six numbers x0,y0,z0,x1,y1,z1, got {text!r}") from None
    if len(vals) != 6:
        raise UserError(f"--bbox: expected six numbers x0,y0,z0,x1,y1,z1, got {len(vals)} in {text!r}")
    return vals  # type: ignore[return-value]


def validate(config: Config) -> None:
    """UserError (one line) for a Config the stage cannot run."""
    if Path(config.out).suffix.lower() not in FORMATS:
        raise UserError(f"{config.out}: unknown mesh format; expected one of {', '.join(FORMATS)}")
    if config.texture and Path(config.out).suffix.lower() == ".ply":
        raise UserError(f"{config.out}: texture needs an .obj or .glb output (PLY holds no texture)")
    if config.texture_source not in ("photos", "field"):
        raise UserError(f"--texture-source: expected photos or field, got {config.texture_source!r}")
    if config.texture_views < 0:
        raise UserError(f"texture_views: expected >= 0, got {config.texture_views}")
    if config.texture_size is not None and not (16 <= config.texture_size <= 8192):
        raise UserError(f"texture_size: expected 16..8192 texels, got {config.texture_size}")
    if not 8 <= config.resolution <= 2048:
        raise UserError(f"--resolution: expected 8..2048, got {config.resolution}")
    if config.threshold not in ("auto", "global") and (
        isinstance(config.threshold, str) or not math.isfinite(float(config.threshold))
    ):
        raise UserError(f"--threshold: expected 'auto', 'global' or a finite number, got {config.threshold!r}")
    check_frame_options(config.frame, config.up, flag="--")
    if config.bbox is not None:
        b = np.asarray(config.bbox, np.float64)
        if b.shape != (6,) or not np.isfinite(b).all() or not (b[3:] > b[:3]).all():
            raise UserError(f"--bbox: expected x0,y0,z0,x1,y1,z1 with x1 > x0, y1 > y0, z1 > z0, got {config.bbox}")
    if config.target_faces != 0 and config.target_faces < 4:
        raise UserError(f"--target-faces: expected 0 (keep all) or at least 4, got {config.target_faces}")
    if config.method not in ("density", "poisson"):
        raise UserError(f"--method: expected 'density' or 'poisson', got {config.method!r}")
    if config.crop not in ("auto", "looked-at", "occupied", "field"):
        raise UserError(f"--crop: expected auto, looked-at, occupied or field, got {config.crop!r}")
    if config.close_gaps < 1:
        raise UserError(f"--close-gaps: expected 1 (off) or more voxels, got {config.close_gaps}")
    if config.threshold_rays < 16:
        raise UserError(f"threshold_rays: expected at least 16, got {config.threshold_rays}")
