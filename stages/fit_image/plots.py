"""fit-image's pictures: the montage of the reconstructions and PSNR against time."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nerfpipe.data.atomic import atomic_path

if TYPE_CHECKING:
    from nerfpipe.stages.fit_image import ModelResult


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def montage(path: Path, image: np.ndarray, recons: list[np.ndarray], results: list[ModelResult]) -> Path:
    """Ground truth and each reconstruction in one row (wrapping after 4), titled with PSNR and seconds."""
    plt = _pyplot()
    panels = [(image, "ground truth")] + [
        (img, f"{r.label}\n{r.psnr:.1f} dB, {r.seconds:.1f} s") for img, r in zip(recons, results, strict=True)
    ]
    cols = min(len(panels), 4)
    rows = math.ceil(len(panels) / cols)
    h, w = image.shape[:2]
    side = max(2.5, min(w, 512) / 100)
    fig, axes = plt.subplots(
        rows, cols, figsize=(side * cols, side * h / w * rows + 0.6 * rows), dpi=100, squeeze=False
    )
    try:
        for ax in axes.flat:
            ax.axis("off")
        for ax, (img, title) in zip(axes.flat, panels, strict=False):
            ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
            ax.set_title(title, fontsize=9)
        fig.tight_layout()
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return path


def plot(path: Path, rows: list[dict], results: list[ModelResult], title: str) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    try:
        for r in results:
            pts = [(row["seconds"], row["psnr"]) for row in rows if row["model"] == r.name]
            ax.plot(*zip(*pts, strict=True), "o-", ms=3, label=f"{r.label} ({r.parameters:,} params)")
        ax.set_xlabel("training seconds")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(f"fit-image {title}: PSNR vs time")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return path
