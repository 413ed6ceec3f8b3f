"""The stiff / extreme-input sweep of the compositing core: one function the tests and the study both call.

Inputs (`sweep_inputs`): one ray per decade of optical depth tau = sigma * delta from 1e-12 to 1e12, each with
four intervals [0, 1), a zero-length [1, 1), [1, 2) and an infinite last one [2, inf) (densities tau, 10 tau,
tau, tau / 2); the same 25 rays again with a finite far, last interval [2, 3) (so the opacity is not simply 1);
an empty ray (sigma = 0 everywhere) and a ray whose first interval has sigma = inf.

`run_sweep(dtype)` composites them in `dtype` (random colours, white background), backpropagates
rgb + depth + acc and returns every output and gradient (`Sweep`); tests/test_compositing.py asserts on it.
`closed_form(...)` is an independent reference in 40-digit decimal arithmetic (Python's `decimal`), evaluated on
the inputs *as rounded to dtype*, so the errors measure the compositing, not the rounding of the inputs.
`summarize(sweep)` gives, per quantity (weights, acc, rgb, depth, Beer-Lambert transmittance), the worst
relative error `|x - ref| / max(|ref|, tiny(dtype))` (tiny: the smallest normal number, so values below the
normal range count absolutely) and whether values and gradients stayed finite.

Conventions follow radiance.compositing: tau = 0 where sigma = 0 or delta = 0, tau = inf where either is inf
(and the other > 0); depth = sum w t_mid / max(acc, eps(dtype of acc)), t_mid = t_start for an infinite interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal, localcontext

import torch
from torch import Tensor

from nerfpipe.radiance.compositing import beer_lambert, composite
from nerfpipe.radiance.safe import eps, tiny

__all__ = [
    "QUANTITIES",
    "TAUS",
    "Sweep",
    "sweep_inputs",
    "ray_labels",
    "run_sweep",
    "closed_form",
    "relative_error",
    "summarize",
]

QUANTITIES = ("weights", "acc", "rgb", "depth", "transmittance")
"""What `summarize` compares with the closed form (transmittance: Beer-Lambert's exp(-sum tau) per ray)."""

DIGITS = 40
"""Decimal digits of the reference arithmetic (Python's `decimal`): exact enough to grade float64."""


TAUS = tuple(10.0**k for k in range(-12, 13))
"""Optical depth sigma * delta of the first interval of each swept ray: one per decade, 1e-12 .. 1e12."""


def sweep_inputs(dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """(sigmas, t_starts, t_ends), each [52, 4] in dtype (rows in the order of `ray_labels`): see the module doc."""
    taus = torch.tensor(TAUS, dtype=torch.float64)  # [25]
    n = taus.shape[0]
    # intervals: [0, 1), a zero-length [1, 1), [1, 2), and [2, inf) (then again with a finite far: [2, 3))
    t0 = torch.tensor([0.0, 1.0, 1.0, 2.0], dtype=torch.float64).expand(2 * n, 4)
    t1 = torch.tensor([[1.0, 1.0, 2.0, math.inf]] * n + [[1.0, 1.0, 2.0, 3.0]] * n, dtype=torch.float64)
    sigmas = torch.stack([taus, taus * 10, taus, taus * 0.5], dim=-1).repeat(2, 1)  # [2n, 4]
    sigmas = torch.cat([sigmas, torch.tensor([[0.0, 0.0, 0.0, 0.0], [math.inf, 1.0, 0.0, 0.0]], dtype=torch.float64)])
    t0, t1 = torch.cat([t0, t0[:2]]), torch.cat([t1, t1[:2]])
    return sigmas.to(dtype), t0.to(dtype), t1.to(dtype)


def ray_labels() -> list[str]:
    """One label per row of `sweep_inputs`: "tau=1e-12, far=inf", ..., "sigma=0", "sigma=inf first"."""
    return (
        [f"tau={t:.0e}, far=inf" for t in TAUS] + [f"tau={t:.0e}, far=3" for t in TAUS] + ["sigma=0", "sigma=inf first"]
    )


@dataclass(frozen=True, kw_only=True)
class Sweep:
    """One dtype's sweep: inputs, `composite` outputs, gradients and Beer-Lambert transmittance."""

    dtype: torch.dtype
    sigmas: Tensor  # [R, S] (detached)
    t_starts: Tensor  # [R, S]
    t_ends: Tensor  # [R, S]
    rgbs: Tensor  # [R, S, 3] (detached)
    background: Tensor  # [3]
    outputs: dict[str, Tensor]  # composite(): rgb [R, 3], depth [R], depth_median [R], acc [R], weights [R, S]
    sigma_grad: Tensor  # [R, S] d(sum rgb + sum depth + sum acc) / d sigma
    rgb_grad: Tensor  # [R, S, 3]
    transmittance: Tensor  # [R] beer_lambert(...)["transmittance"]


def run_sweep(dtype: torch.dtype) -> Sweep:
    """Composite the sweep in `dtype` (forward and backward), as tests/test_compositing.py checks it."""
    sigmas, t0, t1 = sweep_inputs(dtype)
    sigmas.requires_grad_(True)
    rgbs = torch.rand(*sigmas.shape, 3, generator=torch.Generator().manual_seed(0)).to(dtype).requires_grad_(True)
    background = torch.ones(3, dtype=dtype)
    out = composite(sigmas, rgbs, t0, t1, background=background)
    (out["rgb"].sum() + out["depth"].sum() + out["acc"].sum()).backward()
    trans = beer_lambert(sigmas.detach(), t0, t1)["transmittance"]
    return Sweep(
        dtype=dtype,
        sigmas=sigmas.detach(),
        t_starts=t0,
        t_ends=t1,
        rgbs=rgbs.detach(),
        background=background,
        outputs={k: v.detach() for k, v in out.items()},
        sigma_grad=sigmas.grad,
        rgb_grad=rgbs.grad,
        transmittance=trans,
    )


def _tau(sigma: Decimal, delta: Decimal) -> Decimal:
    if sigma == 0 or delta == 0:
        return Decimal(0)
    return Decimal("inf") if sigma.is_infinite() or delta.is_infinite() else sigma * delta


def _exp_neg(x: Decimal) -> Decimal:
    return Decimal(0) if x.is_infinite() else (-x).exp()


def closed_form(
    sigmas: Tensor,  # [R, S]
    t_starts: Tensor,  # [R, S]
    t_ends: Tensor,  # [R, S]
    rgbs: Tensor,  # [R, S, 3]
    background: Tensor,  # [3]
    depth_eps: float,
) -> dict[str, Tensor]:
    """Reference in 40-digit decimal arithmetic, one ray at a time, rounded to float64 at the end:
    weights [R, S], acc [R], rgb [R, 3], depth [R], transmittance [R]."""
    dec = [[[Decimal(v) for v in row] for row in x.double().tolist()] for x in (sigmas, t_starts, t_ends)]
    c = [[[Decimal(v) for v in ci] for ci in row] for row in rgbs.double().tolist()]
    bg = [Decimal(v) for v in background.double().tolist()]
    rows: dict[str, list] = {k: [] for k in QUANTITIES}
    with localcontext() as ctx:
        ctx.prec = DIGITS
        for s, a, b, cr in zip(*dec, c, strict=True):
            taus = [_tau(si, ei - bi) for si, bi, ei in zip(s, a, b, strict=True)]
            mids = [bi if ei.is_infinite() else (bi + ei) / 2 for bi, ei in zip(a, b, strict=True)]
            before, ws = Decimal(0), []
            for tau in taus:
                ws.append(_exp_neg(before) * (1 - _exp_neg(tau)))  # T_i alpha_i
                before += tau
            trans = _exp_neg(before)
            acc = 1 - trans
            rgb = [sum(w * ci[k] for w, ci in zip(ws, cr, strict=True)) + trans * bg[k] for k in range(3)]
            depth = sum(w * m for w, m in zip(ws, mids, strict=True) if w) / max(acc, Decimal(depth_eps))
            for key, value in zip(QUANTITIES, (ws, acc, rgb, depth, trans), strict=True):
                rows[key].append([float(v) for v in value] if isinstance(value, list) else float(value))
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in rows.items()}


def relative_error(x: Tensor, ref: Tensor, dtype: torch.dtype) -> Tensor:
    """|x - ref| / max(|ref|, tiny(dtype)) elementwise, in float64 (inf where x is not finite but ref is)."""
    x, ref = x.double(), ref.double()
    err = (x - ref).abs() / ref.abs().clamp(min=tiny(dtype))
    return torch.where(x == ref, torch.zeros_like(err), err)  # equal infinities: no error


def summarize(sweep: Sweep) -> dict:
    """Worst relative error per quantity (and its ray's label), finiteness of values and gradients, sum w <= 1."""
    dtype = sweep.dtype
    ref = closed_form(
        sweep.sigmas, sweep.t_starts, sweep.t_ends, sweep.rgbs, sweep.background, eps(sweep.outputs["acc"].dtype)
    )
    got = {**{k: sweep.outputs[k] for k in ("weights", "acc", "rgb", "depth")}, "transmittance": sweep.transmittance}
    labels = ray_labels()
    worst, where = {}, {}
    for k in QUANTITIES:
        err = relative_error(got[k], ref[k], dtype)
        per_ray = err.reshape(err.shape[0], -1).amax(dim=1)  # [R]
        i = int(per_ray.argmax())
        worst[k], where[k] = float(per_ray[i]), labels[i]
    values = [sweep.outputs[k] for k in ("weights", "rgb", "depth", "acc")] + [sweep.transmittance]
    return {
        "dtype": str(dtype).removeprefix("torch."),
        "eps": eps(dtype),
        "worst_rel_error": worst,
        "worst_at": where,
        "values_finite": all(bool(torch.isfinite(v).all()) for v in values),
        "gradients_finite": bool(torch.isfinite(sweep.sigma_grad).all() and torch.isfinite(sweep.rgb_grad).all()),
        "weights_sum_le_one": bool((sweep.outputs["weights"].double().sum(-1) <= 1 + eps(dtype)).all()),
    }
