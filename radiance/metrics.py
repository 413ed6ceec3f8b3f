"""Image-quality figures shared by training, rendering and evaluation.

Images are in [0, 1]. PSNR = -10 log10(MSE), with the MSE floored at 1e-10 (so identical images give 100 dB,
not inf).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MSE_FLOOR", "psnr_from_mse", "psnr"]

MSE_FLOOR = 1e-10
"""Smallest MSE used in PSNR: caps PSNR at 100 dB for identical images."""


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error over values in [0, 1]."""
    return -10.0 * math.log10(max(float(mse), MSE_FLOOR))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB between two images (any shape, values in [0, 1]), computed in float64."""
    return psnr_from_mse(float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))
