"""Per-image appearance (NeRF-W's appearance embeddings, GLO codes): a small learned code per training image
that changes the colour head's output only; density, and so geometry, stay shared by every image.

Conventions: view k of the training views (train split order) owns a code c_k [dim]. A linear head maps it to an
affine colour transform of the field's colour at every sample of that view's rays,
    rgb'(x) = A_k rgb(x) + b_k,      (A_k, b_k) = (I + M_k, m_k),  [M_k | m_k] = head(c_k)  [3, 4],
which models exposure, white balance and colour casts (the usual causes of per-photo differences in a capture).
Because it is affine, compositing commutes with it: sum_i w_i (A rgb_i + b) = A rgb + acc b, so it is applied
exactly to a ray's composited colour (before the background). The head starts at zero (every transform is the
identity), the codes at N(0, 0.01^2) so that both receive gradients.

Evaluation rules (novel views have no code):
- `mean` (default): the mean code over the training images. The head is linear, so this renders with the mean
  transform; when the photos' variations average out (exposure around the right level), that is the scene's own
  colour. `None` as the view selects it.
- `half` (NeRF-W's protocol, `eval --appearance-rule half`): each test view's code is fitted to the left half of
  its photo with the field frozen, and the view is scored on the right half only. The transform is affine in the
  code (linear head) and acts on composited colours, so the fit is one ridge least-squares solve on the left
  half's rendered (colour, opacity): `fit_code`. `apply_transform` applies its transform to the
  view rendered without appearance (exact: the transform acts on composited colours).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["Appearance", "fit_code", "apply_transform", "EVAL_RULE", "EVAL_RULES"]

EVAL_RULE = "mean code over the training images (linear head: the mean per-image colour transform)"
EVAL_RULES = {
    "mean": EVAL_RULE,
    "half": "NeRF-W: each test view's code fitted (ridge least squares, field frozen) on the left half of its "
    "photo; PSNR/SSIM on the right half only",
}
"""eval's --appearance-rule values and what each does (eval's JSON records the text)."""


class Appearance(nn.Module):
    """Codes [V, dim] and the head mapping a code to an affine colour transform (3x3 + offset)."""

    def __init__(self, n_views: int, dim: int = 8, seed: int = 0) -> None:
        super().__init__()
        if n_views < 1 or dim < 1:
            raise ValueError(f"expected n_views >= 1 and dim >= 1, got {n_views}, {dim}")
        self.n_views, self.dim = int(n_views), int(dim)
        gen = torch.Generator().manual_seed(seed)  # own generator: the run's random stream stays as without codes
        self.codes = nn.Parameter(0.01 * torch.randn(n_views, dim, generator=gen))  # [V, dim]
        self.head = nn.Linear(dim, 12)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def transform(self, view: Tensor | None) -> tuple[Tensor, Tensor]:
        """view [B] (training view indices) or None (the evaluation rule) -> A [B or 1, 3, 3], b [B or 1, 3]."""
        code = self.codes.mean(0, keepdim=True) if view is None else self.codes[view.long()]
        return self.code_transform(code)

    def code_transform(self, code: Tensor) -> tuple[Tensor, Tensor]:
        """code [B, dim] -> A [B, 3, 3], b [B, 3]."""
        out = self.head(code)  # [B, 12]
        eye = torch.eye(3, dtype=out.dtype, device=out.device)
        return eye + out[:, :9].reshape(-1, 3, 3), out[:, 9:]

    def forward(self, rgb: Tensor, acc: Tensor, background: Tensor, view: Tensor | None) -> Tensor:
        """A ray's colour rgb [B, 3] composited on background ([3] or [B, 3]) with opacity acc [B] -> the same
        with the view's transform applied to the field's part (the background is left as it is)."""
        return apply_transform(self.transform(view), rgb, acc, background)

    def param_groups(self, lr: float) -> list[dict]:
        """Codes and head at lr / 20, like the field's colour MLP."""
        return [{"params": list(self.parameters()), "lr": lr / 20.0, "lr_scale": 1.0 / 20.0}]

    def to_dict(self) -> dict:
        return {"n_views": self.n_views, "dim": self.dim, "state": self.state_dict()}

    @classmethod
    def from_dict(cls, doc: dict) -> Appearance:
        app = cls(int(doc["n_views"]), int(doc["dim"]))
        app.load_state_dict(doc["state"])
        return app


def apply_transform(ab: tuple[Tensor, Tensor], rgb: Tensor, acc: Tensor, background: Tensor) -> Tensor:
    """The affine (A [B or 1, 3, 3], b [B or 1, 3]) on the field's part of composited colours rgb [B, 3]."""
    a, b = ab
    bg = background.to(rgb).expand_as(rgb)
    fg = rgb - (1 - acc)[:, None] * bg  # sum_i w_i rgb_i
    return (a @ fg[:, :, None])[..., 0] + acc[:, None] * b + (1 - acc)[:, None] * bg


@torch.no_grad()
def fit_code(
    appearance: Appearance, rgb: Tensor, acc: Tensor, background: Tensor, target: Tensor, ridge: float = 1e-3
) -> Tensor:
    """The code [dim] whose transform best maps the field's own composited colours rgb [N, 3] (rendered without
    appearance; opacity acc [N], on background [3]) to the photo's target [N, 3]: ridge least squares around the
    mean code (the prediction is affine in the code: the head is linear); ridge is relative to the mean squared
    Jacobian."""
    if rgb.shape != target.shape or rgb.ndim != 2 or rgb.shape[1] != 3 or acc.shape != rgb.shape[:1]:
        raise ValueError(
            f"expected rgb, target [N, 3] and acc [N], got {tuple(rgb.shape)}, {tuple(target.shape)}, "
            f"{tuple(acc.shape)}"
        )
    rgb, acc, target = rgb.double(), acc.double(), target.double()
    bg = background.to(rgb).reshape(3)
    fg = rgb - (1 - acc)[:, None] * bg
    w, bias = appearance.head.weight.double(), appearance.head.bias.double()  # [12, dim], [12]

    def predict(out: Tensor) -> Tensor:  # head output [12] -> [N, 3]
        a = torch.eye(3, dtype=out.dtype) + out[:9].reshape(3, 3)
        return fg @ a.T + acc[:, None] * out[9:] + (1 - acc)[:, None] * bg

    base = predict(bias)  # [N, 3] at code 0
    jac = torch.stack([(predict(bias + w[:, j]) - base).reshape(-1) for j in range(w.shape[1])], dim=1)  # [3N, dim]
    mean = appearance.codes.double().mean(0)
    lam = ridge * float((jac**2).sum(0).mean()) + 1e-12
    lhs = jac.T @ jac + lam * torch.eye(w.shape[1], dtype=jac.dtype)
    rhs = jac.T @ (target - base).reshape(-1) + lam * mean
    return torch.linalg.solve(lhs, rhs).to(appearance.codes.dtype)
