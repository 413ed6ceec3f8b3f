"""The voxel network: a 2-D convolutional encoder to an embedding, 3-D transposed convolutions to a grid of
occupancy logits (3D-R2N2's and Pix2Vox's shape; Pix2Vox-F's size, trained from scratch: no ImageNet backbone).

Input [B, 4, SIDE, SIDE] (`inputs.prepare`), output logits [B, RES, RES, RES] indexed (i, j, k) = (x, y, z) of
the view frame (`data.synthetic.shape_views`). Sigmoid of a logit = the probability that the cell is occupied.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["VoxelNet", "PRIOR_LOGIT"]

PRIOR_LOGIT = -2.5
"""The last layer's initial bias: sigmoid(-2.5) = 0.076, about the share of occupied cells of the family shapes
(the first steps learn shapes, not the class balance)."""


def _down(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)
    )


def _up(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.ConvTranspose3d(cin, cout, 4, stride=2, padding=1, bias=False), nn.BatchNorm3d(cout), nn.ReLU(inplace=True)
    )


class VoxelNet(nn.Module):
    """Encoder 64 -> 4 pixels (four stride-2 convolutions), a linear map to a 2^3 volume of `width` channels,
    decoder 2 -> 32 cells (four stride-2 transposed convolutions), a 1x1x1 convolution to logits."""

    def __init__(self, *, side: int = 64, res: int = 32, width: int = 64, channels: int = 4) -> None:
        super().__init__()
        if side % 16 or res % 16:
            raise ValueError(f"expected side and res multiples of 16, got {side} and {res}")
        self.side, self.res, self.width, self.channels = side, res, width, channels
        self.encoder = nn.Sequential(
            nn.Conv2d(channels, 32, 3, padding=1, bias=False),
            nn.BatchNorm2d(32),
            nn.ReLU(inplace=True),
            _down(32, 64),
            _down(64, 128),
            _down(128, 256),
            _down(256, 128),
        )
        self.seed = res // 16
        self.embed = nn.Sequential(
            nn.Flatten(), nn.Linear(128 * (side // 16) ** 2, width * self.seed**3), nn.ReLU(inplace=True)
        )
        self.decoder = nn.Sequential(_up(width, 64), _up(64, 48), _up(48, 24), _up(24, 12), nn.Conv3d(12, 1, 1))
        nn.init.constant_(self.decoder[-1].bias, PRIOR_LOGIT)

    def config(self) -> dict:
        return {"side": self.side, "res": self.res, "width": self.width, "channels": self.channels}

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, C, side, side] -> logits [B, res, res, res]
        if x.ndim != 4 or x.shape[1:] != (self.channels, self.side, self.side):
            raise ValueError(f"expected [B, {self.channels}, {self.side}, {self.side}], got {tuple(x.shape)}")
        z = self.embed(self.encoder(x)).view(-1, self.width, self.seed, self.seed, self.seed)
        # the decoder's volume is (channel, x, y, z): returned as [B, x, y, z]
        return self.decoder(z)[:, 0]
