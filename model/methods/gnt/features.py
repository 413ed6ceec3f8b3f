"""GNT's image feature extractors: photo [V, 4, H, W] (premultiplied rgb, alpha) -> features [V, C, H/2, W/2].

- `Shallow`: three 3x3 convolutions (the first with stride 2): the source document's cheap variant.
- `ResUNet`: GNT's ResNet-style encoder-decoder cut to CPU size: two residual stages at 1/2 and 1/4 resolution, the
  deeper one upsampled and joined to the shallower by a skip connection, features at 1/2 resolution.
Both end at half resolution, so a source image's feature texel (i, j) covers its pixels 2i, 2i + 1 (`Extractor.stride`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["EXTRACTORS", "Shallow", "ResUNet", "make_extractor"]


class Shallow(nn.Module):
    stride = 2

    def __init__(self, channels: int):
        super().__init__()
        self.channels = channels
        self.convs = nn.ModuleList(
            [
                nn.Conv2d(4, channels, 3, stride=2, padding=1),
                nn.Conv2d(channels, channels, 3, padding=1),
                nn.Conv2d(channels, channels, 3, padding=1),
            ]
        )

    def forward(self, images: Tensor) -> Tensor:  # [V, 4, H, W] -> [V, C, H/2, W/2]
        x = images
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i + 1 < len(self.convs):
                x = F.relu(x)
        return x


class _Residual(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.a = nn.Conv2d(cin, cout, 3, stride=stride, padding=1)
        self.b = nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1, stride=stride) if (stride != 1 or cin != cout) else nn.Identity()
        self.norm_a, self.norm_b = nn.GroupNorm(4, cout), nn.GroupNorm(4, cout)

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.norm_a(self.a(x)))
        return F.relu(self.norm_b(self.b(y)) + self.skip(x))


class ResUNet(nn.Module):
    stride = 2

    def __init__(self, channels: int):
        super().__init__()
        self.channels = channels
        self.stage1 = _Residual(4, channels, 2)  # 1/2
        self.stage2 = _Residual(channels, 2 * channels, 2)  # 1/4
        self.up = nn.Conv2d(3 * channels, channels, 3, padding=1)
        self.out = nn.Conv2d(channels, channels, 1)

    def forward(self, images: Tensor) -> Tensor:  # [V, 4, H, W] -> [V, C, H/2, W/2]
        half = self.stage1(images)
        quarter = self.stage2(half)
        up = F.interpolate(quarter, size=half.shape[-2:], mode="bilinear", align_corners=False)
        return self.out(F.relu(self.up(torch.cat([half, up], dim=1))))


EXTRACTORS = {"shallow": Shallow, "resunet": ResUNet}


def make_extractor(kind: str, channels: int) -> nn.Module:
    if kind not in EXTRACTORS:
        raise ValueError(f"expected an extractor in {sorted(EXTRACTORS)}, got {kind!r}")
    return EXTRACTORS[kind](channels)
