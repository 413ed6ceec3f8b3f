"""What `train` writes about a finished run: the PSNR-vs-time plot and the manifest's used / left_out records."""

from __future__ import annotations

import resource
from pathlib import Path
from typing import Any

import torch

from data.atomic import atomic_path
from data.transforms import Scene, is_forward_facing
from model.field_model import FieldModel

__all__ = ["plot_psnr", "used_and_left_out"]


def plot_psnr(path: Path, rows: list[dict], title: str) -> None:
    """train and test PSNR against wall-clock seconds, from metrics.csv rows, as a PNG (atomic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for key, style in (("train_psnr", "-"), ("test_psnr", "o-")):
        pts = [(float(r["seconds"]), float(r[key])) for r in rows if r.get(key) not in (None, "")]
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=key.replace("_", " "), markersize=3)
    ax.set_xlabel("wall-clock seconds")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def used_and_left_out(
    *, scene: Scene, model: FieldModel, device: torch.device, batch_rays: int, steps: int, seconds: float,
    samples_per_ray: float, train_idx: tuple[int, ...], test_idx: tuple[int, ...],
    chosen: list[int], test_psnr: float | None,
) -> tuple[dict[str, Any], dict[str, str]]:  # fmt: skip
    """The manifest's record of what the run used and what it left out (and why)."""
    ndc = model.ndc
    peak = torch.cuda.max_memory_allocated() if device.type == "cuda" else None
    used: dict[str, Any] = {
        "batch_rays": batch_rays,
        "field": model.field.config(),
        "device": str(device),
        "cpu_threads": torch.get_num_threads() if device.type == "cpu" else None,
        "steps": steps,
        "train_seconds": round(seconds, 3),
        "train_views": len(train_idx),
        "test_views": len(test_idx),
        "test_psnr_full_images": test_psnr,
        "test_views_full_eval": [test_idx[v] for v in chosen],
        "background": model.background.describe(),
        "view_dependent": model.field.view_dependent,
        "scene_type": "forward-facing" if is_forward_facing(scene) else "bounded / 360",
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_cuda_mb": round(peak / 2**20, 1) if peak is not None else None,
    }
    if model.grid is not None:
        used["occupancy_skip_fraction"] = round(model.grid.skip_fraction, 4)
        used["samples_per_ray"] = round(samples_per_ray, 2)
        used["march_step"] = {"train": model.step_size, "render": model.step_size * model.render_step_factor}
    used["scene_model"] = "ndc" if ndc is not None else ("contract" if model.contraction is not None else "box")
    if model.contraction is not None:
        used["contraction"] = {**model.contraction.to_dict(), "field_box": model.aabb.tolist(),
                               "note": "field and occupancy grid live in contracted space; the scene's box "
                                       "maps to [-1, 1]^3 and everything beyond it into the shell up to 2"}  # fmt: skip
    if ndc is not None:
        used["ndc"] = {**ndc.to_dict(), "box": model.aabb.tolist(),
                       "note": "field and occupancy grid live in NDC of the mean camera (radiance.ndc); depths "
                               "are mapped back to scene units"}  # fmt: skip
    left_out = {}
    if ndc is not None:
        left_out["aabb"] = "forward-facing: the field spans the NDC frustum (near plane to infinity), not the aabb"
    elif is_forward_facing(scene):
        left_out["ndc"] = "forward-facing scene trained in its box or contracted because that was asked for"
    else:
        left_out["ndc"] = "360-degree scene: NDC only applies to forward-facing captures"
    if ndc is None and model.contraction is None:
        left_out["contraction"] = "the scene's box holds everything the photos show (alpha or a plain background)"
    if not test_idx:
        left_out["test_psnr"] = "scene has no test or val split"
    if model.grid is None:
        left_out["occupancy_grid"] = "vanilla field uses the paper's stratified + hierarchical sampling"
    return used, left_out
