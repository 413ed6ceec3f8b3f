"""Per-image appearance (NeRF-W's appearance embeddings, GLO codes): a small learned code per training image
that changes the colour head's output only; density, and so geometry, stay shared by every image.

Conventions: view k of the training views (train split order) owns a code c_k [dim]. A linear head maps it to an
affine colour transform of the field's colour at every sample of that view's rays,
    rgb'(x) = A_k rgb(x) + b_k,      (A_k, b_k) = (I + M_k, m_k),  [M_k | m_k] = head(c_k)  [3, 4],
which models exposure, white balance and colour casts (the usual causes of per-photo differences in a capture).
Because it is affine, compositing commutes with it: sum_i w_i (A rgb_i + b) = A rgb + acc b, so it is applied
exactly to a ray's composited colour (before the background). The head starts at zero (every transform is the
identity), the codes at N(0, 0.01^2) so that both receive gradients.

Evaluation rule (novel views have no code): the mean code over the training images. The head is linear, so
this renders with the mean transform; when the photos' variations average out (exposure around the right
level), that is the scene's own colour. `None` as the view selects it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["Appearance", "EVAL_RULE"]

EVAL_RULE = "mean code over the training images (linear head: the mean per-image colour transform)"


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
        out = self.head(code)  # [B, 12]
        eye = torch.eye(3, dtype=out.dtype, device=out.device)
        return eye + out[:, :9].reshape(-1, 3, 3), out[:, 9:]

    def forward(self, rgb: Tensor, acc: Tensor, background: Tensor, view: Tensor | None) -> Tensor:
        """A ray's colour rgb [B, 3] composited on background ([3] or [B, 3]) with opacity acc [B] -> the same
        with the view's transform applied to the field's part (the background is left as it is)."""
        bg = background.to(rgb).expand_as(rgb)
        fg = rgb - (1 - acc)[:, None] * bg  # sum_i w_i rgb_i
        a, b = self.transform(view)
        return (a @ fg[:, :, None])[..., 0] + acc[:, None] * b + (1 - acc)[:, None] * bg

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
