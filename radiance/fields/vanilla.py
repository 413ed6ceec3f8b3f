"""The NeRF paper's MLP (Mildenhall et al. 2020), exactly: reference for the fast field.

- gamma(x) with L = 10 and gamma(d) with L = 4, identity included (63 and 27 inputs);
- 8 fully connected ReLU layers of 256, the encoded position concatenated again to the input of the
  fifth layer (skip);
- sigma head (one linear from the 8th layer's output), then a 256 feature (no activation), concatenated
  with gamma(d), one 128 ReLU layer, RGB with a sigmoid.
Sampling (64 stratified coarse samples, 128 importance fine samples, two networks) is the trainer's job;
`VanillaNeRF` holds both networks.

Positions are used in the scene frame as they are (the paper feeds world coordinates of the Blender
scenes, within about [-1.5, 1.5]); density uses softplus instead of the paper's ReLU so it never dies at
init and stays finite (docs/DESIGN.md: density activation).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfpipe.radiance.fields.base import Field, check_points
from nerfpipe.radiance.fields.encodings import encoded_size, positional_encoding

__all__ = ["NeRFMLP", "VanillaNeRF"]


class NeRFMLP(Field):
    """One NeRF network (coarse or fine)."""

    def __init__(
        self,
        *,
        pos_freqs: int = 10,
        dir_freqs: int = 4,
        width: int = 256,
        depth: int = 8,
        skip: int = 4,
        has_color: bool = True,
        view_dependent: bool = True,
    ) -> None:
        super().__init__()
        self.pos_freqs, self.dir_freqs, self.width, self.depth, self.skip = pos_freqs, dir_freqs, width, depth, skip
        self.has_color = has_color
        self.view_dependent = view_dependent and has_color
        in_x = encoded_size(3, pos_freqs)
        in_d = encoded_size(3, dir_freqs) if self.view_dependent else 0
        layers = []
        for i in range(depth):
            fan_in = in_x if i == 0 else width
            if i == skip + 1:  # the 5th layer's output is concatenated with gamma(x) (paper code: skips=[4])
                fan_in = width + in_x
            layers.append(nn.Linear(fan_in, width))
        self.layers = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(width, 1)
        if has_color:
            self.feature = nn.Linear(width, width)
            self.rgb_hidden = nn.Linear(width + in_d, width // 2)
            self.rgb_head = nn.Linear(width // 2, 3)

    def _trunk(self, x: Tensor) -> Tensor:
        gx = positional_encoding(x, self.pos_freqs)
        h = gx
        for i, layer in enumerate(self.layers):
            if i == self.skip + 1:
                h = torch.cat([h, gx], dim=-1)
            h = F.relu(layer(h))
        return h

    @staticmethod
    def _sigma(raw: Tensor) -> Tensor:
        return F.softplus(raw.squeeze(-1).clamp(max=60.0))

    def density(self, x: Tensor) -> Tensor:
        check_points(x)
        return self._sigma(self.sigma_head(self._trunk(x)))

    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        return self.forward(x, d)[1]

    def forward(self, x: Tensor, d: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        check_points(x)
        h = self._trunk(x)
        sigma = self._sigma(self.sigma_head(h))
        if not self.has_color:
            return sigma, None
        feat = self.feature(h)
        if self.view_dependent:
            if d is None:
                raise ValueError("this field is view dependent: pass directions d [N, 3]")
            feat = torch.cat([feat, positional_encoding(d, self.dir_freqs)], dim=-1)
        rgb = torch.sigmoid(self.rgb_head(F.relu(self.rgb_hidden(feat))))
        return sigma, rgb


class VanillaNeRF(Field):
    """Coarse + fine NeRF networks. As a `Field` it answers with the fine network."""

    n_coarse: int = 64
    n_fine: int = 128

    def __init__(
        self, *, has_color: bool = True, view_dependent: bool = True, n_coarse: int = 64, n_fine: int = 128
    ) -> None:
        super().__init__()
        self.has_color = has_color
        self.view_dependent = view_dependent and has_color
        self.n_coarse, self.n_fine = n_coarse, n_fine
        kw = dict(has_color=has_color, view_dependent=view_dependent)
        self.coarse = NeRFMLP(**kw)
        self.fine = NeRFMLP(**kw)

    def density(self, x: Tensor) -> Tensor:
        return self.fine.density(x)

    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        return self.fine.color(x, d)

    def forward(self, x: Tensor, d: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        return self.fine(x, d)

    def config(self) -> dict:
        return {
            "kind": "vanilla",
            "has_color": self.has_color,
            "view_dependent": self.view_dependent,
            "n_coarse": self.n_coarse,
            "n_fine": self.n_fine,
        }
