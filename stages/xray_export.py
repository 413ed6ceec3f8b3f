"""Stage `xray-export`: what a reader looks at from an X-ray run: slice montages, a rotating DRR/MIP video, a mesh.

    nerfpipe xray-export RUN_DIR OUT_DIR [--frames 36] [--fps 12] [--iso auto|VALUE] [--slices 5]

From the reconstructed volume (the field sampled on the scene grid, `model.xray.XrayRun.volume`):
- `slices.png`: the middle slice along x, y and z (rows), reconstruction | ground truth | |difference| (columns,
  when the ground truth is known), one grey window [0, max of the ground truth (else of the reconstruction)];
  `slices_x.png`, `slices_y.png`, `slices_z.png`: `slices` evenly spaced slices, reconstruction over truth.
- `drr_mip.mp4`: a full turn about the rotation axis, `frames` views with the scene's detector: the digitally
  reconstructed radiograph (the line integral, white = most attenuation, as radiographs show bone) beside the
  maximum-intensity projection.
- `mesh.ply`: marching cubes (scikit-image) at the iso-attenuation `--iso` (1 / length unit; auto: Otsu's
  threshold of the volume, which separates air from tissue), vertices in the scene's world frame and length unit
  (mm; the volume centred on the rotation axis), faces wound counter-clockwise seen from outside.
- `manifest.json` (last).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import config_to_json, output_folder, write_manifest
from nerfpipe.data.video import to_uint8, video_writer, write_png
from nerfpipe.data.volumes import iso_surface
from nerfpipe.model.device import cpu_threads
from nerfpipe.model.xray import XrayRun, load_xray_run
from nerfpipe.radiance.xray import detector_rays, siddon_project

__all__ = ["Config", "Outputs", "run", "parse_iso", "iso_level"]

VERSION = "1"


def parse_iso(text: str | None) -> float | None:
    """'auto' -> None; a number -> float (the CLI parser for --iso)."""
    if text is None or str(text).strip().lower() == "auto":
        return None
    try:
        return float(text)
    except ValueError:
        raise UserError(f"iso: expected 'auto' or an attenuation value, got {text!r}") from None


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """X-ray run directory (xray-train)."""
    out_dir: Path
    """Output folder (slices*.png, drr_mip.mp4, mesh.ply, manifest.json)."""
    frames: int = 36
    """Video frames over one full turn."""
    fps: float = 12.0
    """Video frame rate."""
    slices: int = 5
    """Slices per axis in slices_{x,y,z}.png."""
    iso: float | None = None
    """Mesh iso-attenuation in 1/length unit (mm: 1/mm); None (auto): Otsu's threshold of the volume."""
    mesh: bool = True
    """Write mesh.ply."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    threads: int | None = None
    """torch intra-op threads (None: torch's default)."""
    overwrite: bool = False
    """Replace an earlier output in out_dir (set aside in OUT_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    slices: Path
    video: Path
    mesh: Path | None
    manifest: Path
    iso: float | None
    faces: int


def _grey(img: np.ndarray, hi: float) -> np.ndarray:
    return _zoom(to_uint8(np.asarray(img, np.float32) / (hi if hi > 0 else 1.0)))


def _slice(vol: np.ndarray, axis: int, index: int) -> np.ndarray:
    """A slice shown with its first remaining axis across and the second one up (so z points up)."""
    s = np.take(vol, index, axis=axis)
    return np.flipud(s.T)


def _montage(rows: list[list[np.ndarray]], gap: int = 2) -> np.ndarray:
    """uint8 tiles in rows -> one image, tiles padded to the largest size, with gaps."""
    h = max(t.shape[0] for r in rows for t in r)
    w = max(t.shape[1] for r in rows for t in r)
    ncol = max(len(r) for r in rows)
    out = np.zeros((len(rows) * (h + gap) - gap, ncol * (w + gap) - gap), np.uint8)
    for i, r in enumerate(rows):
        for j, t in enumerate(r):
            out[i * (h + gap) : i * (h + gap) + t.shape[0], j * (w + gap) : j * (w + gap) + t.shape[1]] = t
    return out


def _zoom(img: np.ndarray, size: int = 256) -> np.ndarray:
    """Nearest-neighbour enlargement of small slices so that the longer side reaches about `size` pixels."""
    k = max(1, size // max(img.shape))
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1)


def write_slices(out_dir: Path, vol: np.ndarray, gt: np.ndarray | None, n: int) -> list[Path]:
    """slices.png (middle slices: reconstruction | truth | |difference|) and slices_{x,y,z}.png (n per axis)."""
    hi = float((gt if gt is not None else vol).max())
    rows = []
    for axis in range(3):
        mid = vol.shape[axis] // 2
        row = [_grey(_slice(vol, axis, mid), hi)]
        if gt is not None:
            row += [_grey(_slice(gt, axis, mid), hi), _grey(np.abs(_slice(vol, axis, mid) - _slice(gt, axis, mid)), hi)]
        rows.append(row)
    paths = [write_png(out_dir / "slices.png", _montage(rows))]
    for axis, name in enumerate("xyz"):
        idx = np.linspace(0, vol.shape[axis] - 1, n + 2)[1:-1].round().astype(int)
        tiles = [[_grey(_slice(vol, axis, i), hi) for i in idx]]
        if gt is not None:
            tiles.append([_grey(_slice(gt, axis, i), hi) for i in idx])
        paths.append(write_png(out_dir / f"slices_{name}.png", _montage(tiles)))
    return paths


def write_video(path: Path, xrun: XrayRun, vol: torch.Tensor, frames: int, fps: float, progress: Progress) -> Path:
    """DRR (line integral over [0, the largest measured], white = most attenuation, as radiographs show bone)
    | MIP (attenuation over [0, the volume's max]), over one turn, with the scene's detector."""
    g = xrun.geometry
    nv, nu = g.detector_shape
    task = progress.add_task("drr/mip video", total=frames)
    mip_hi = float(vol.max()) or 1.0
    drr_hi = float(xrun.scene.projections.max()) or 1.0
    with video_writer(path, fps=fps) as writer:
        for k in range(frames):
            gk = g.with_angles([2 * math.pi * k / frames])
            o, d = detector_rays(gk, 0)
            p = siddon_project(vol, xrun.grid.spacing, xrun.grid.center, o, d).reshape(nv, nu).numpy()
            m = siddon_project(vol, xrun.grid.spacing, xrun.grid.center, o, d, reduce="max").reshape(nv, nu).numpy()
            mip = to_uint8(m / mip_hi)
            frame = np.concatenate([to_uint8(p / drr_hi), np.full((nv, 4), 0, np.uint8), mip], axis=1)
            writer.write(np.repeat(frame[..., None], 3, axis=-1))
            progress.advance(task)
    return path


def iso_level(vol: np.ndarray) -> float:
    """Otsu's threshold of the volume (air vs the rest)."""
    from skimage.filters import threshold_otsu

    return float(threshold_otsu(np.asarray(vol, np.float32)))


def write_mesh(path: Path, xrun: XrayRun, vol: np.ndarray, iso: float) -> int:
    """Marching cubes at `iso` in world coordinates (length unit); returns the face count."""
    import trimesh

    if not (vol.min() < iso < vol.max()):
        raise UserError(f"iso: {iso:.4g} is outside the volume's attenuation range [{vol.min():.4g}, {vol.max():.4g}]")
    # attenuation grows into the object: faces wind counter-clockwise seen from outside
    spacing = np.asarray(xrun.grid.spacing)
    verts, faces = iso_surface(vol, iso, xrun.grid.box[0] + 0.5 * spacing, spacing)  # voxel centres
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False)
    with atomic_path(path, suffix=".ply") as tmp:
        mesh.export(tmp)
    return int(faces.shape[0])


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """See the module doc; torch's CPU threads are set to config.threads for the call and restored after."""
    with output_folder(config.out_dir, overwrite=config.overwrite):
        with cpu_threads(config.threads):
            return _run(config, progress)


def _run(config: Config, progress: Progress | None) -> Outputs:
    started = time.time()
    progress = progress or NO_PROGRESS
    if config.frames < 1 or config.slices < 1:
        raise UserError(f"frames, slices: expected >= 1, got {config.frames}, {config.slices}")
    xrun = load_xray_run(config.run_dir, config.device)
    out_dir = Path(config.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    vol_t = xrun.volume()
    vol = vol_t.numpy()
    slices = write_slices(out_dir, vol, xrun.scene.volume, config.slices)
    video = write_video(out_dir / "drr_mip.mp4", xrun, vol_t, config.frames, config.fps, progress)
    mesh_path, iso, faces = None, None, 0
    if config.mesh:
        iso = config.iso if config.iso is not None else iso_level(vol)
        mesh_path = out_dir / "mesh.ply"
        faces = write_mesh(mesh_path, xrun, vol, iso)
    manifest = write_manifest(
        out_dir,
        stage="xray-export",
        started=started,
        version=VERSION,
        config=config_to_json(config),
        inputs=[Path(config.run_dir) / "checkpoint.pt"],
        outputs=[*slices, video, *([mesh_path] if mesh_path else [])],
        used={
            "iso": iso,
            "iso_rule": "given" if config.iso is not None else "otsu",
            "faces": faces,
            "frame": f"scene world frame, {xrun.scene.length_unit}, rotation axis +z",
        },
        left_out={} if config.mesh else {"mesh": "--no-mesh"},
    )
    return Outputs(
        out_dir=out_dir, slices=slices[0], video=video, mesh=mesh_path, manifest=manifest, iso=iso, faces=faces
    )
