"""Reconstruction metrics as the CT-NeRF papers (NAF, SAX-NeRF, R2-Gaussian) define them.

- `psnr_3d(pred, gt)`: 10 log10(range^2 / MSE) over every voxel, range = max(gt) - min(gt) (the ground truth's
  dynamic range, so the figure does not depend on the attenuation unit); MSE floored as in radiance.metrics.
- `ssim_3d(pred, gt)`: mean of 2-D SSIM (scikit-image, 7x7 uniform window, the same data range) over every
  slice along each of the three axes, averaged over the axes.
- `psnr_projections`, `ssim_projections`: the same on stacks of projections [V, n_v, n_u] (2-D SSIM per view),
  with the measured projections' range.
Arrays are numpy, computed in float64.
"""

from __future__ import annotations

import numpy as np

from nerfpipe.radiance.metrics import psnr_from_mse

__all__ = ["psnr_3d", "ssim_3d", "psnr_projections", "ssim_projections", "data_range"]


def data_range(gt: np.ndarray) -> float:
    """max(gt) - min(gt), or 1 for a constant array."""
    gt = np.asarray(gt, np.float64)
    r = float(gt.max() - gt.min()) if gt.size else 0.0
    return r if r > 0 else 1.0


def _check(pred: np.ndarray, gt: np.ndarray, ndim: int) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.ndim != ndim:
        raise ValueError(f"expected two {ndim}-D arrays of one shape, got {pred.shape} and {gt.shape}")
    return pred, gt


def psnr_3d(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR (dB) of a volume against the ground truth, over the ground truth's range."""
    pred, gt = _check(pred, gt, 3)
    r = data_range(gt)
    return psnr_from_mse(float(np.mean((pred - gt) ** 2)) / (r * r))


def _ssim_2d(a: np.ndarray, b: np.ndarray, r: float) -> float:
    from skimage.metrics import structural_similarity

    if min(a.shape) < 7:  # skimage's window is 7 x 7
        return float("nan")
    return float(structural_similarity(a, b, data_range=r))


def ssim_3d(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean 2-D SSIM over the slices along x, y and z (then averaged over the three axes)."""
    pred, gt = _check(pred, gt, 3)
    r = data_range(gt)
    per_axis = []
    for axis in range(3):
        p, g = np.moveaxis(pred, axis, 0), np.moveaxis(gt, axis, 0)
        per_axis.append(np.nanmean([_ssim_2d(p[i], g[i], r) for i in range(p.shape[0])]))
    return float(np.mean(per_axis))


def psnr_projections(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR (dB) of projection stacks [V, n_v, n_u] over the measured projections' range."""
    pred, gt = _check(pred, gt, 3)
    r = data_range(gt)
    return psnr_from_mse(float(np.mean((pred - gt) ** 2)) / (r * r))


def ssim_projections(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean 2-D SSIM over the views of projection stacks [V, n_v, n_u]."""
    pred, gt = _check(pred, gt, 3)
    r = data_range(gt)
    return float(np.nanmean([_ssim_2d(pred[i], gt[i], r) for i in range(pred.shape[0])]))
