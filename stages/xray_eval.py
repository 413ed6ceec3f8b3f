"""Stage `xray-eval`: score an X-ray run as the CT-NeRF papers do, with the FDK baseline beside it, to JSON.

    nerfpipe xray-eval RUN_DIR OUT.json [--ground-truth VOLUME] [--no-baseline]

- Volume (radiance.ct_metrics): the field sampled at the scene grid's voxel centres against the ground truth
  (the scene's `volume.npy`, or `--ground-truth` on the same grid): `psnr_3d` (over the ground truth's range),
  `ssim_3d` (mean 2-D SSIM over the slices along x, y and z), `mae` (1 / length unit).
- Projections: the reconstructed volume re-projected through every held-out (`test`) and training view with the
  exact voxel projector, against the scene's projections: `proj_psnr`, `proj_ssim` per split.
- Baseline (default on): FDK (radiance.fdk, Ram-Lak) on the same training views, scored the same way.
Writes OUT.json and OUT.manifest.json (last).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.atomic import write_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import config_to_json, sidecar, write_manifest
from nerfpipe.data.volumes import read_volume
from nerfpipe.model.device import cpu_threads
from nerfpipe.model.xray import XrayRun, load_xray_run
from nerfpipe.radiance.ct_metrics import psnr_3d, psnr_projections, ssim_3d, ssim_projections
from nerfpipe.radiance.fdk import fdk
from nerfpipe.radiance.xray import project_views

__all__ = ["Config", "Outputs", "run", "volume_metrics", "projection_metrics"]

VERSION = "1"


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """X-ray run directory (xray-train)."""
    out: Path
    """Output JSON file."""
    ground_truth: Path | None = None
    """Ground-truth volume on the scene grid (.npy, .mat, .raw, .nii); default: the scene's volume.npy."""
    baseline: bool = True
    """Also reconstruct with FDK from the same training views and score it."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    threads: int | None = None
    """torch intra-op threads (None: torch's default)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out: Path
    manifest: Path
    result: dict
    """What OUT.json holds."""


def volume_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    return {
        "psnr_3d": round(psnr_3d(pred, gt), 4),
        "ssim_3d": round(ssim_3d(pred, gt), 4),
        "mae": float(np.mean(np.abs(np.asarray(pred, np.float64) - gt))),
    }


def projection_metrics(volume: torch.Tensor, run: XrayRun) -> dict:
    """Re-projected volume vs the scene's projections, per split (PSNR over the measured range, mean SSIM)."""
    scene, out = run.scene, {}
    for split in ("test", "train"):
        views = list(scene.split(split))
        if not views:
            continue
        pred = project_views(volume, scene.grid.spacing, scene.grid.center, scene.geometry.subset(views)).numpy()
        meas = scene.projections[views]
        out[split] = {
            "views": len(views),
            "proj_psnr": round(psnr_projections(pred, meas), 4),
            "proj_ssim": round(ssim_projections(pred, meas), 4),
        }
    return out


def _ground_truth(config: Config, run: XrayRun) -> np.ndarray | None:
    if config.ground_truth is None:
        return run.scene.volume
    vol = read_volume(config.ground_truth, spacing=run.grid.spacing)
    if tuple(vol.data.shape) != tuple(run.grid.shape):
        raise UserError(
            f"ground_truth: shape {list(vol.data.shape)} differs from the scene grid {list(run.grid.shape)}"
        )
    return vol.data


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """See the module doc; torch's CPU threads are set to config.threads for the call and restored after."""
    with cpu_threads(config.threads):
        return _run(config, progress)


def _run(config: Config, progress: Progress | None) -> Outputs:
    started = time.time()
    progress = progress or NO_PROGRESS
    out = Path(config.out)
    if out.suffix.lower() != ".json":
        raise UserError(f"{out}: expected a .json output path")
    xrun = load_xray_run(config.run_dir, config.device)
    gt = _ground_truth(config, xrun)
    task = progress.add_task("xray-eval", total=3)
    vol = xrun.volume()
    progress.advance(task)
    result: dict = {
        "run_dir": str(config.run_dir),
        "grid": {"shape": list(xrun.grid.shape), "spacing": list(xrun.grid.spacing), "unit": xrun.scene.length_unit},
    }
    result["field"] = {
        **(volume_metrics(vol.numpy(), gt) if gt is not None else {}),
        "projections": projection_metrics(vol, xrun),
    }
    progress.advance(task)
    if config.baseline:
        train = list(xrun.scene.split("train"))
        t0 = time.perf_counter()
        rec = fdk(torch.from_numpy(xrun.scene.projections[train]), xrun.geometry.subset(train), xrun.grid)
        result["fdk"] = {
            **(volume_metrics(rec.numpy(), gt) if gt is not None else {}),
            "seconds": round(time.perf_counter() - t0, 2),
            "projections": projection_metrics(rec, xrun),
        }
        if gt is not None:
            result["gain_over_fdk_db"] = round(result["field"]["psnr_3d"] - result["fdk"]["psnr_3d"], 3)
    progress.advance(task)
    if gt is None:
        result["ground_truth"] = None
    # flat headline figures for the CLI summary and for scripts
    result["psnr_3d"] = result["field"].get("psnr_3d")
    result["ssim_3d"] = result["field"].get("ssim_3d")
    test = result["field"]["projections"].get("test", {})
    result["proj_psnr"], result["proj_ssim"] = test.get("proj_psnr"), test.get("proj_ssim")
    write_json(out, result)
    manifest = write_manifest(
        out.parent,
        name=sidecar(out, "manifest.json").name,
        stage="xray-eval",
        started=started,
        version=VERSION,
        config=config_to_json(config),
        inputs=[Path(config.run_dir) / "checkpoint.pt"] + ([config.ground_truth] if config.ground_truth else []),
        outputs=[out],
        used={
            "volume": "field sampled at the scene grid's voxel centres",
            "projections": "volume re-projected with radiance.xray.siddon_project",
        },
        left_out={} if gt is not None else {"psnr_3d, ssim_3d": "no ground-truth volume"},
    )
    return Outputs(out=out, manifest=manifest, result=result)
