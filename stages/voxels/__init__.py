"""Stage `voxels`: one or more photos of one object, with its mask, to a 32^3 occupancy grid and a mesh.

    nerfpipe voxels chair.png OUT_DIR                                  # a PNG whose alpha is the object's mask
    nerfpipe voxels a.jpg b.jpg OUT_DIR --masks a_mask.png,b_mask.png --azimuths 0,90

The network (`model.voxels`, weights shipped in the repository: `make pretrain-voxels`) sees each photo cropped
about its mask with the background removed (`model.voxels.inputs`), and predicts the object in the photo's view
frame: viewer-centred and upright (x to the photo's right, y away from the camera, z up; the object centred and
scaled to fit the cube [-0.5, 0.5]^3; the camera assumed level: roll tilts the prediction). Several photos need
their cameras' azimuths about the object (degrees, counter-clockwise seen from above; a turntable that turns the
object counter-clockwise by 30 deg per photo gives 0,-30,-60,...): each grid is turned into the first photo's
frame and the probabilities averaged (`model.voxels.fuse`).

A stage of its own, not a method of `train --method` (decision, docs/VOXELS.md): its input is unposed photos, its
output a volume with no cameras; so it writes its own mesh and preview, and `mesh`/`render` are not needed.

Outputs under OUT_DIR:
  occupancy.npy   float32 [32, 32, 32]: probability that each cell is occupied, indexed (x, y, z) (frame above)
  occupancy.json  the frame, the cell size, the photos and their azimuths, the weights used
  mesh.ply        marching cubes of the probabilities at `level`, vertices in the same frame (left out, and said
                  so, when no cell reaches it)
  preview.png     each photo's input, then the grid rendered from the photo's side, its right, behind, its left
  manifest.json   written last
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.atomic import write_bytes, write_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.images import as_float_rgb, exif_orientation, read_image_file, upright
from nerfpipe.data.masks import read_mask
from nerfpipe.data.rundir import output_folder, write_config, write_manifest
from nerfpipe.data.video import write_png
from nerfpipe.data.volumes import iso_surface, write_npy
from nerfpipe.model.device import resolve_device
from nerfpipe.model.voxels.fuse import fuse
from nerfpipe.model.voxels.infer import occupancy
from nerfpipe.model.voxels.inputs import prepare
from nerfpipe.model.voxels.preview import render_grid
from nerfpipe.model.voxels.weights import load_net

__all__ = ["Config", "Outputs", "run", "read_photo", "predict"]

PREVIEW_SIDE = 160
PREVIEW_ELEVATION = 20.0


@dataclass(frozen=True, kw_only=True)
class Config:
    images: tuple[Path, ...]
    """Photos of one object: PNGs whose alpha is its mask, or any photos with --masks."""
    out_dir: Path
    """Folder for occupancy.npy, occupancy.json, mesh.ply, preview.png and manifest.json (created)."""
    masks: tuple[Path, ...] = ()
    """The object's mask of each photo, in order (white = object); none: the photos' alpha channels."""
    azimuths: tuple[float, ...] = ()
    """With several photos: each camera's azimuth about the object, degrees, counter-clockwise seen from above."""
    weights: str = "pretrained"
    """The network: 'pretrained' (shipped with nerfpipe) or a weights.pt of pretrain-voxels."""
    level: float = 0.5
    """Probability at which a cell counts as occupied (the mesh's iso-level)."""
    mirror: bool = True
    """Also predict from each photo mirrored left-right and average (model.voxels.infer; twice the passes)."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    overwrite: bool = False
    """Replace an earlier output in out_dir."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    occupancy: Path
    mesh: Path | None
    preview: Path
    photos: int
    occupied: int
    """Cells at or above `level`."""
    level: float


def read_photo(image: Path, mask: Path | None) -> tuple[np.ndarray, np.ndarray]:
    """An image file and its mask (a file, or the image's alpha) -> rgb [H, W, 3], mask [H, W], float32 in
    [0, 1], upright (the photo's EXIF orientation applied; a mask file is taken as it matches the photo: upright,
    or as stored and turned with it); UserError in one line when there is no usable mask."""
    decoded = read_image_file(image)
    orientation = exif_orientation(decoded.data)
    stored = decoded.pixels
    px = as_float_rgb(upright(stored, orientation))  # [H, W, 3|4] RGB(A)
    rgb = np.ascontiguousarray(px[..., :3])
    if mask is not None:
        m = read_mask(mask)
        if m.shape != px.shape[:2] and m.shape == stored.shape[:2]:
            m = upright(m, orientation)  # drawn on the pixels as stored
        if m.shape != px.shape[:2]:
            raise UserError(
                f"{mask}: mask is {m.shape[1]}x{m.shape[0]} but its photo {image} is {px.shape[1]}x{px.shape[0]}"
            )
    elif px.shape[-1] == 4:
        m = px[..., 3]
        if m.min() >= 1.0:
            raise UserError(
                f"{image}: its alpha is opaque everywhere (no object mask): give a PNG whose alpha "
                "cuts the object out, or a mask file"
            )
    else:
        raise UserError(f"{image}: no alpha channel: give a PNG whose alpha is the object's mask, or a mask file")
    if not (m >= 0.5).any():
        raise UserError(f"{mask or image}: the mask is empty (no pixel >= 0.5): nothing to predict a shape of")
    return rgb, m


def predict(net: torch.nn.Module, inputs: torch.Tensor, azimuths_deg: list[float], *, mirror: bool) -> torch.Tensor:
    """inputs [V, 4, S, S] -> the fused probabilities [R, R, R] in the first photo's view frame."""
    prob = occupancy(net, inputs, mirror=mirror)  # [V, R, R, R]
    if len(prob) == 1:
        return prob[0]
    return fuse(prob, torch.tensor([math.radians(a) for a in azimuths_deg], dtype=torch.float64))


def _check(config: Config) -> None:
    n = len(config.images)
    if n == 0:
        raise UserError("voxels: expected at least one photo")
    if config.masks and len(config.masks) != n:
        raise UserError(f"voxels: expected one mask per photo ({n}), got {len(config.masks)}")
    if n > 1 and len(config.azimuths) != n:
        raise UserError(
            f"voxels: {n} photos need {n} azimuths (each camera's azimuth about the object, degrees), "
            f"got {len(config.azimuths)}"
        )
    if n == 1 and len(config.azimuths) > 1:
        raise UserError(f"voxels: one photo takes at most one azimuth, got {len(config.azimuths)}")
    if not 0.0 < config.level < 1.0:
        raise UserError(f"voxels: expected 0 < level < 1, got {config.level}")


def _mesh_ply(prob: np.ndarray, level: float) -> bytes | None:
    """Marching cubes of prob [R, R, R] at `level` (zero-padded: a closed surface), vertices in the view frame."""
    import trimesh

    if not (prob >= level).any():
        return None
    cell = 1.0 / prob.shape[0]
    verts, faces = iso_surface(prob, level, np.full(3, 0.5 * cell - 0.5), np.full(3, cell))  # cell centres
    return trimesh.Trimesh(verts.astype(np.float32), faces, process=False).export(file_type="ply")


def _preview(inputs: torch.Tensor, prob: torch.Tensor, level: float) -> np.ndarray:
    """The preview image: uint8 [H, W, 3] RGB."""
    tiles = []
    for x in inputs:  # the network's view of each photo, on white
        m = x[3:].numpy()
        rgb = x[:3].numpy() + (1 - m)
        tile = torch.nn.functional.interpolate(torch.from_numpy(rgb)[None], size=PREVIEW_SIDE, mode="bilinear")[0]
        tiles.append(tile.permute(1, 2, 0).numpy())
    tiles += [render_grid(prob, turn, PREVIEW_ELEVATION, PREVIEW_SIDE, level) for turn in (0.0, 90.0, 180.0, 270.0)]
    return (np.clip(np.concatenate(tiles, axis=1), 0.0, 1.0) * 255).round().astype(np.uint8)


def run(config: Config) -> Outputs:
    _check(config)
    started = time.time()
    device = resolve_device(config.device)
    masks = list(config.masks) or [None] * len(config.images)
    photos = [read_photo(Path(img), Path(m) if m else None) for img, m in zip(config.images, masks, strict=True)]
    net, provenance = load_net(config.weights, device)
    inputs = torch.stack([prepare(rgb, m, net.side) for rgb, m in photos])  # [V, 4, S, S]
    azimuths = list(config.azimuths) or [0.0]
    prob = predict(net, inputs, azimuths, mirror=config.mirror)
    with output_folder(config.out_dir, overwrite=config.overwrite):
        out = Path(config.out_dir)
        write_config(out, config)
        occupancy = write_npy(out / "occupancy.npy", prob.numpy().astype(np.float32))
        res = prob.shape[0]
        write_json(
            out / "occupancy.json",
            {
                "shape": [res, res, res],
                "index": "occupancy[i, j, k] is the cell centred at (x_i, y_j, z_k) = ((i, j, k) + 0.5) / res - 0.5",
                "frame": "view frame of the first photo: x to its right (horizontal), y horizontal away from its "
                "camera, z up (the camera assumed level); the object centred and scaled so that it fits the "
                "vertical cylinder of radius 0.5 and height 1 about the origin",
                "bounds": [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]],
                "cell": 1.0 / res,
                "units": "the object's size: max(2 x its horizontal reach from its vertical axis, its height) = 1",
                "values": "probability that the cell is occupied",
                "level": config.level,
                "photos": [str(p) for p in config.images],
                "azimuths_deg": azimuths,
                "mirror": "mean of each photo's prediction and its mirrored photo's, mirrored back"
                if config.mirror
                else "none (one prediction a photo)",
                "fusion": "mean of the probabilities, each photo's grid turned into the first photo's frame"
                if len(photos) > 1
                else "none (one photo)",
                "weights": str(config.weights),
                "weights_provenance": {
                    k: provenance.get(k) for k in ("stage", "steps", "seconds", "commit", "families")
                },
            },
        )
        ply = _mesh_ply(prob.numpy(), config.level)
        mesh = write_bytes(out / "mesh.ply", ply) if ply is not None else None
        preview = write_png(out / "preview.png", _preview(inputs, prob, config.level))
        occupied = int((prob >= config.level).sum())
        left_out = {} if mesh else {"mesh.ply": f"no cell reaches the level {config.level}"}
        write_manifest(
            out,
            stage="voxels",
            started=started,
            inputs=[*config.images, *config.masks],
            outputs=["occupancy.npy", "occupancy.json", "preview.png", "config.json"] + (["mesh.ply"] if mesh else []),
            used={
                "photos": len(photos),
                "mirror": config.mirror,
                "occupied_cells": occupied,
                "level": config.level,
                "device": str(device),
            },
            left_out=left_out,
        )
        return Outputs(
            out_dir=out,
            occupancy=occupancy,
            mesh=mesh,
            preview=preview,
            photos=len(photos),
            occupied=occupied,
            level=config.level,
        )
