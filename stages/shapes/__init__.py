"""Stage `shapes`: a dataset of photos of family shapes with their exact occupancy (what `pretrain-voxels` trains
on and `make bench-voxels` scores).

    nerfpipe shapes OUT_DIR [--families chair,table] [--count 300] [--views 6] [--first-seed 0]

For each family and each seed in [first_seed, first_seed + count): the shape (`data.synthetic.families`) and
`views` photos of it (`data.synthetic.shape_views.shape_photos`: random cameras, textures, lights, backgrounds and
mask edges), each turned into the network's input (`model.voxels.inputs.prepare`) and stored with the occupancy of
its view frame. Objects are drawn in `workers` processes; the file is the same whatever their number.

Outputs under OUT_DIR:
  shapes.npz     inputs uint8 [N, 4, SIDE, SIDE] (x 255), bits uint8 [N, RES^3 / 8] (numpy packbits of the
                 occupancy [RES, RES, RES], indexed (x, y, z) of the view frame), family int [N] (index into
                 `families`), families str [F], seed int [N], azimuth, elevation, distance float [N] (radians, units)
  manifest.json  written last: families, counts, seconds
"""

from __future__ import annotations

import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import output_folder, write_config, write_manifest
from nerfpipe.data.synthetic.families import FAMILIES, HELD_OUT, TRAINED
from nerfpipe.data.synthetic.shape_views import RES, shape_photos
from nerfpipe.model.voxels.inputs import SIDE, prepare

__all__ = ["Config", "Outputs", "run", "RENDER_SIDE"]

RENDER_SIDE = 112
"""Side of the rendered photos, pixels (each is cropped about its object and resampled to the input's side)."""


@dataclass(frozen=True, kw_only=True)
class Config:
    out_dir: Path
    """Folder for shapes.npz and manifest.json (created)."""
    families: tuple[str, ...] = TRAINED
    """Families drawn (data.synthetic.families.FAMILIES); the default leaves out the held-out one."""
    count: int = 300
    """Objects per family."""
    views: int = 6
    """Photos per object."""
    first_seed: int = 0
    """Seeds first_seed .. first_seed + count - 1 (pretraining and benchmarks use apart ranges)."""
    workers: int = 0
    """Processes drawing objects (0: one per CPU core)."""
    overwrite: bool = False
    """Replace an earlier output in out_dir."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    shapes: Path
    examples: int
    seconds: float


def _draw(job: tuple[str, int, int]) -> dict[str, np.ndarray]:
    family, seed, views = job
    torch.set_num_threads(1)
    _, photos = shape_photos(family, seed, views, RENDER_SIDE)
    x = np.stack([(prepare(p.rgb, p.mask).numpy() * 255).round().astype(np.uint8) for p in photos])
    bits = np.stack([np.packbits(p.occupancy.reshape(-1)) for p in photos])
    return {
        "inputs": x,
        "bits": bits,
        "azimuth": np.array([p.azimuth for p in photos]),
        "elevation": np.array([p.elevation for p in photos]),
        "distance": np.array([p.distance for p in photos]),
    }


def run(config: Config, progress: Progress | None = None) -> Outputs:
    unknown = [f for f in config.families if f not in FAMILIES]
    if unknown or not config.families:
        raise UserError(f"shapes: expected families among {sorted(FAMILIES)}, got {list(config.families)}")
    if config.count < 1 or config.views < 1 or config.first_seed < 0 or config.workers < 0:
        raise UserError("shapes: expected count >= 1, views >= 1, first_seed >= 0 and workers >= 0")
    progress = progress or NO_PROGRESS
    started = time.time()
    jobs = [(f, config.first_seed + i, config.views) for f in config.families for i in range(config.count)]
    workers = config.workers or multiprocessing.cpu_count()
    with output_folder(config.out_dir, overwrite=config.overwrite):
        out = Path(config.out_dir)
        write_config(out, config)
        task = progress.add_task("shapes", total=len(jobs))
        parts = []
        if workers == 1:
            for job in jobs:
                parts.append(_draw(job))
                progress.advance(task)
        else:
            ctx = multiprocessing.get_context("fork")
            with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
                for part in pool.map(_draw, jobs, chunksize=4):
                    parts.append(part)
                    progress.advance(task)
        data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        data["family"] = np.repeat([config.families.index(f) for f, _, _ in jobs], config.views)
        data["seed"] = np.repeat([s for _, s, _ in jobs], config.views)
        data["families"] = np.array(config.families)
        data["res"] = np.array(RES)
        data["side"] = np.array(SIDE)
        with atomic_path(out / "shapes.npz") as tmp, open(tmp, "wb") as f:
            np.savez(f, **data)
        seconds = time.time() - started
        write_manifest(
            out,
            stage="shapes",
            started=started,
            outputs=["shapes.npz", "config.json"],
            used={
                "families": list(config.families),
                "held_out_family": HELD_OUT,
                "objects": len(jobs),
                "examples": len(data["seed"]),
                "seeds": [config.first_seed, config.first_seed + config.count - 1],
                "render_side": RENDER_SIDE,
                "input_side": SIDE,
                "res": RES,
                "workers": workers,
                "seconds": round(seconds, 1),
            },
        )
        return Outputs(out_dir=out, shapes=out / "shapes.npz", examples=len(data["seed"]), seconds=seconds)
