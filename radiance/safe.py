"""Safe numerics: dtype-aware epsilons and tolerances, guarded exp/log/div/sqrt, density activations.

Conventions:
- `eps(dtype)` is `torch.finfo(dtype).eps` (machine epsilon: the gap between 1 and the next float).
- `tol(dtype)` gives `(rtol, atol)` for comparing a computation in `dtype` against a float64 reference.
- Every helper keeps the input's dtype and device, and returns finite values and finite gradients for finite
  inputs (and for +-inf where the docstring says so).
- Density activations map a raw network output to sigma >= 0 (units: 1 / scene length) and never overflow
  to inf in fp16, bf16 or fp32.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "eps",
    "tiny",
    "tol",
    "max_exp_input",
    "safe_exp",
    "safe_log",
    "safe_div",
    "safe_sqrt",
    "shifted_softplus",
    "trunc_exp",
    "TRUNC_EXP_MAX",
]

# (rtol, atol) for "this dtype's computation agrees with the float64 closed form".
_TOL: dict[torch.dtype, tuple[float, float]] = {
    torch.float16: (1e-2, 1e-3),
    torch.bfloat16: (5e-2, 1e-2),
    torch.float32: (1e-5, 1e-6),
    torch.float64: (1e-10, 1e-12),
}

# trunc_exp's input is clamped to this in fp32/fp64 (exp(15) ~ 3.3e6, instant-ngp / torch-ngp's value).
TRUNC_EXP_MAX = 15.0


def eps(dtype: torch.dtype) -> float:
    """Machine epsilon of a floating dtype (fp16: 9.8e-4, bf16: 7.8e-3, fp32: 1.2e-7, fp64: 2.2e-16)."""
    return torch.finfo(dtype).eps


def tiny(dtype: torch.dtype) -> float:
    """Smallest positive normal number of a floating dtype."""
    return torch.finfo(dtype).tiny


def tol(dtype: torch.dtype) -> tuple[float, float]:
    """(rtol, atol) to compare a result computed in `dtype` with a float64 reference."""
    if dtype not in _TOL:
        raise ValueError(f"expected a floating dtype in {list(_TOL)}, got {dtype}")
    return _TOL[dtype]


def max_exp_input(dtype: torch.dtype, margin: float = 1.0) -> float:
    """Largest x (minus `margin`) with exp(x) finite in `dtype` (fp16: 10.1, bf16/fp32: 87.7)."""
    return math.log(torch.finfo(dtype).max) - margin


def safe_exp(x: Tensor) -> Tensor:
    """exp(x) with x clamped so the result (and its gradient) stays finite in x's dtype."""
    return torch.exp(x.clamp(max=max_exp_input(x.dtype)))


def safe_log(x: Tensor) -> Tensor:
    """log(x) with x clamped to the smallest normal number: finite for x <= 0 (gradient 0 there)."""
    return torch.log(x.clamp(min=tiny(x.dtype)))


def safe_div(num: Tensor, den: Tensor, min_den: float | None = None) -> Tensor:
    """num / den for a non-negative denominator (e.g. accumulated opacity), clamped to `min_den`.

    `min_den` defaults to eps(dtype), as docs/DESIGN.md asks for divisions by opacity.
    """
    lo = eps(den.dtype) if min_den is None else min_den
    return num / den.clamp(min=lo)


def safe_sqrt(x: Tensor) -> Tensor:
    """sqrt(x) with x clamped to eps(dtype): finite value and gradient at and below 0."""
    return torch.sqrt(x.clamp(min=eps(x.dtype)))


def shifted_softplus(x: Tensor, shift: float = -1.0) -> Tensor:
    """sigma = softplus(x + shift) (mip-NeRF's density activation with shift -1).

    torch's softplus is linear above its threshold, so it cannot overflow: softplus(x) <= x + log 2.
    """
    return torch.nn.functional.softplus(x + shift)


def _trunc_exp_max(dtype: torch.dtype) -> float:
    # fp16 overflows at exp(11.09); keep headroom so sigma * delta and sums of a few stay finite.
    return min(TRUNC_EXP_MAX, max_exp_input(dtype, margin=2.0))


class _TruncExp(torch.autograd.Function):
    """exp with a clamped input, forward and backward (torch-ngp's trunc_exp, clamped forward too)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=_trunc_exp_max(x.dtype)))

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        hi = _trunc_exp_max(x.dtype)
        # Gradient of exp at the clamped point (not 0 above it, so a saturated density can still come down).
        return grad * torch.exp(x.clamp(min=-hi, max=hi))


def trunc_exp(x: Tensor) -> Tensor:
    """sigma = exp(x) with x clamped to min(15, log(max(dtype)) - 2) (fp16: 9.1).

    The backward pass uses exp of the clamped input, so gradients stay finite and non-zero for large x.
    """
    return _TruncExp.apply(x)
