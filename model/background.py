"""The colour a ray shows where the field is empty: fixed, random per ray (training only), or learned.

Modes (train --background; the names nerfstudio's `background_color` and instant-ngp use):
- `fixed`: one colour [3] in [0, 1] for training and evaluation (black, white, or a detected plain colour);
- `random`: a uniform random colour per ray in training (photos with alpha: it makes empty space transparent
  whatever the colour; opaque photos: every pixel must come from the field), its colour (white unless given)
  for evaluation and rendering;
- `learned`: sigmoid of a 3-vector optimised with the field; evaluation uses its current value;
- `plain`: images composited on one plain colour, whose pixels around the object were marked transparent (alpha
  0): the rays the caller marks `random` get a random colour in training (the transparent ones: empty space must
  be empty; with pose refinement also the object's pixels not of the plain colour: the object must be opaque;
  `model.views.Views.random_behind` marks them), every other ray the plain colour, as the image was made
  (a partly covered edge pixel is alpha x object + (1 - alpha) x colour: the field can say so; a random colour
  behind it would force a dark, opaque halo); evaluation on the plain colour.
Photos with alpha are composited on the same colour the model is (radiance.compositing.over_background).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["Background", "MODES"]

MODES = ("fixed", "random", "learned", "plain")


class Background(torch.nn.Module):
    """A background model: `train_colour(n)` for a batch of n rays, `eval_colour()` for evaluation."""

    def __init__(self, mode: str, colour: tuple[float, float, float] = (1.0, 1.0, 1.0)):
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"expected background mode in {MODES}, got {mode!r}")
        c = torch.tensor(colour, dtype=torch.float32).clamp(1e-3, 1 - 1e-3)
        self.mode = mode
        self.colour = torch.nn.Parameter(torch.logit(c), requires_grad=mode == "learned")  # [3] logits
        self.register_buffer("fixed", torch.tensor(colour, dtype=torch.float32))  # [3]

    def eval_colour(self) -> Tensor:  # [3]
        return torch.sigmoid(self.colour) if self.mode == "learned" else self.fixed

    def train_colour(
        self,
        n: int,
        generator: torch.Generator | None = None,
        random: Tensor | None = None,  # [n] bool: the rays that get a random colour (`plain` mode)
    ) -> Tensor:  # [n, 3] or [3]
        if self.mode in ("random", "plain"):
            rand = torch.rand(n, 3, generator=generator).to(self.fixed.device)
            if self.mode == "random":
                return rand
            if random is None or random.shape != (n,):
                raise ValueError(f"plain background: expected random [{n}] bool, got {random!r:.60}")
            return torch.where(random.to(rand.device)[:, None], rand, self.fixed)
        return self.eval_colour()

    def params(self) -> list[torch.nn.Parameter]:
        """What the optimiser updates (only a learned colour)."""
        return [self.colour] if self.mode == "learned" else []

    def describe(self) -> dict:
        return {"mode": self.mode, "eval_colour": [round(float(v), 4) for v in self.eval_colour().detach().cpu()]}
