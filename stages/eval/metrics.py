"""eval's image metrics: SSIM (scikit-image), LPIPS where its weights are on this machine (never downloaded), and the
mean of a column that may have gaps."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["ALEXNET_WEIGHTS", "ssim", "lpips_status", "mean_of"]


ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"
"""torchvision's AlexNet checkpoint file name, which lpips loads from the torch hub cache."""


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM of two [H, W, 3] images in [0, 1] (skimage defaults: 7x7 uniform window)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0))


def lpips_status() -> tuple[Any | None, str | None]:
    """(an LPIPS-AlexNet callable, None) when the package and every weight file are present offline, else
    (None, reason). Never downloads."""
    try:
        import lpips  # noqa: F401
    except ImportError:
        return None, "the lpips package is not installed (nerfpipe never downloads it or its weights)"
    hub = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS
    lin = Path(lpips.__file__).parent / "weights" / "v0.1" / "alex.pth"
    missing = [str(p) for p in (hub, lin) if not p.is_file()]
    if missing:
        return None, f"LPIPS weights not present offline: {', '.join(missing)} (never downloaded)"
    try:
        model = lpips.LPIPS(net="alex", verbose=False).eval()
    except Exception as exc:  # any failure to build it offline is a reason, not a crash
        return None, f"LPIPS could not be built offline: {type(exc).__name__}: {exc}"

    @torch.no_grad()
    def score(pred: np.ndarray, gt: np.ndarray) -> float:
        def to_t(x):
            return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].float() * 2 - 1

        return float(model(to_t(pred), to_t(gt)).item())

    return score, None


def mean_of(values: list[float | None]) -> float | None:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else None
