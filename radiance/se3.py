"""SE(3) and SO(3) exponential and logarithm maps (maths only), differentiable and safe near zero and near pi.

Conventions:
- A twist `xi [..., 6]` is (omega, v): omega [..., 3] the rotation vector (axis times angle, radians), v [..., 3]
  the translational part. `se3_exp(xi)` is the 4x4 rigid transform [[R, V v], [0, 1]] with R = exp(omega^) and
  V = I + B omega^ + C omega^2 (the left Jacobian of SO(3)); `se3_log` is its inverse (angle in [0, pi]).
- Batched over leading dimensions; any float dtype. Near theta = 0 the coefficients
  A = sin(t)/t, B = (1 - cos t)/t^2, C = (t - sin t)/t^3 and D = (1 - A / 2B)/t^2 use their Taylor series (the
  closed forms cancel catastrophically there), with the branch switch chosen per dtype (`_SMALL`), and the
  square root of theta^2 is never taken at 0, so values and gradients are finite at exactly zero.
- Near theta = pi `so3_log` takes the axis from the symmetric part of R (R + R^T)/2 = I + (1 - cos t)(n n^T - I),
  whose largest diagonal entry gives a well-conditioned column, and the sign from the skew part.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["hat", "vee", "so3_exp", "so3_log", "se3_exp", "se3_log"]

_SMALL = {torch.float64: 1e-5, torch.float32: 1e-3, torch.float16: 1e-2, torch.bfloat16: 1e-2}
"""theta^2 below which the Taylor series replace the closed forms (their next term is below eps there)."""
_NEAR_PI_COS = -0.9
"""cos(theta) below which so3_log takes the axis from the symmetric part of R (theta > ~154 degrees)."""


def _check(x: Tensor, n: int, name: str) -> None:
    if x.shape[-1] != n:
        raise ValueError(f"expected {name} [..., {n}], got {tuple(x.shape)}")


def hat(w: Tensor) -> Tensor:
    """w [..., 3] -> the skew matrix w^ [..., 3, 3] with w^ x = w cross x."""
    _check(w, 3, "w")
    z = torch.zeros_like(w[..., 0])
    x, y, c = w.unbind(-1)
    return torch.stack([z, -c, y, c, z, -x, -y, x, z], dim=-1).reshape(*w.shape[:-1], 3, 3)


def vee(m: Tensor) -> Tensor:
    """The vector of the skew-symmetric part of m [..., 3, 3] -> [..., 3] (vee(w^) = w)."""
    x, y, z = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    return 0.5 * torch.stack([x, y, z], dim=-1)


def _coefficients(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A, B, C of theta^2 [...] (see the module docstring), Taylor series below _SMALL."""
    small = theta2 < _SMALL.get(theta2.dtype, 1e-3)
    t2 = torch.where(small, torch.ones_like(theta2), theta2)  # no sqrt(0) on either branch
    t = torch.sqrt(t2)
    s, c = torch.sin(t), torch.cos(t)
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, s / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - c) / t2)
    cc = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (t - s) / (t2 * t))
    return a, b, cc


def so3_exp(w: Tensor) -> Tensor:
    """Rotation vectors w [..., 3] -> rotation matrices [..., 3, 3] (Rodrigues)."""
    _check(w, 3, "w")
    k = hat(w)
    a, b, _ = _coefficients((w * w).sum(-1))
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(r: Tensor) -> Tensor:
    """Rotation matrices r [..., 3, 3] -> rotation vectors [..., 3] with angle in [0, pi]."""
    if r.shape[-2:] != (3, 3):
        raise ValueError(f"expected r [..., 3, 3], got {tuple(r.shape)}")
    cos = ((r.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    sin_axis = vee(r)  # sin(theta) n
    sin2 = (sin_axis * sin_axis).sum(-1)
    small = sin2 < _SMALL.get(r.dtype, 1e-3)
    near_pi = cos < _NEAR_PI_COS
    # General: theta = atan2(sin, cos), w = theta / sin * sin_axis.
    sin = torch.sqrt(torch.where(small | near_pi, torch.ones_like(sin2), sin2))
    theta = torch.atan2(sin, cos)
    general = (theta / sin)[..., None] * sin_axis
    # Near 0: theta / sin(theta) = 1 + sin^2 / 6 + 3 sin^4 / 40 + ...
    near_zero = (1 + sin2 / 6 + 3 * sin2**2 / 40)[..., None] * sin_axis
    # Near pi: n n^T = (sym - cos I) / (1 - cos); the column of the largest diagonal entry, normalised.
    sym = 0.5 * (r + r.transpose(-1, -2))
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    nn_t = (sym - cos[..., None, None] * eye) / torch.where(near_pi, 1 - cos, torch.ones_like(cos))[..., None, None]
    col = nn_t.diagonal(dim1=-2, dim2=-1).argmax(-1)
    v = torch.gather(nn_t, -1, col[..., None, None].expand(*col.shape, 3, 1))[..., 0]
    n = v / torch.sqrt((v * v).sum(-1, keepdim=True).clamp_min(torch.finfo(r.dtype).tiny))
    sign = torch.where((n * sin_axis).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(r.dtype)
    theta_pi = torch.atan2(torch.sqrt(sin2.clamp_min(torch.finfo(r.dtype).tiny)), cos)  # finite gradient at pi
    at_pi = sign * n * theta_pi[..., None]
    return torch.where(near_pi[..., None], at_pi, torch.where(small[..., None], near_zero, general))


def se3_exp(xi: Tensor) -> Tensor:
    """Twists xi [..., 6] = (omega, v) -> rigid transforms [..., 4, 4] = [[exp(omega^), V v], [0, 1]]."""
    _check(xi, 6, "xi")
    w, v = xi[..., :3], xi[..., 3:]
    k = hat(w)
    a, b, c = _coefficients((w * w).sum(-1))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    kk = k @ k
    rot = eye + a[..., None, None] * k + b[..., None, None] * kk
    jac = eye + b[..., None, None] * k + c[..., None, None] * kk
    t = (jac @ v[..., None])[..., 0]
    top = torch.cat([rot, t[..., None]], dim=-1)  # [..., 3, 4]
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def se3_log(m: Tensor) -> Tensor:
    """Rigid transforms m [..., 4, 4] (or [..., 3, 4]) -> twists [..., 6] = (omega, v), angle in [0, pi]."""
    if m.shape[-1] != 4 or m.shape[-2] not in (3, 4):
        raise ValueError(f"expected m [..., 4, 4] or [..., 3, 4], got {tuple(m.shape)}")
    w = so3_log(m[..., :3, :3])
    theta2 = (w * w).sum(-1)
    a, b, _ = _coefficients(theta2)
    small = theta2 < _SMALL.get(m.dtype, 1e-3)
    # V^-1 = I - w^/2 + D w^2, D = (1 - A / (2 B)) / theta^2 = 1/12 + theta^2/720 + theta^4/30240 + ...
    d = torch.where(
        small,
        1 / 12 + theta2 / 720 + theta2**2 / 30240,
        (1 - a / (2 * b)) / torch.where(small, torch.ones_like(theta2), theta2),
    )
    k = hat(w)
    eye = torch.eye(3, dtype=m.dtype, device=m.device)
    v_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    v = (v_inv @ m[..., :3, 3:4])[..., 0]
    return torch.cat([w, v], dim=-1)
