"""fit-image's two models of an image: a Fourier-feature MLP and a TensoRF-style grid over (u, v)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from nerfpipe.radiance.fields import TensoRF
from nerfpipe.radiance.fields.encodings import encoded_size, positional_encoding

GRID_RANK = 16


def pixel_coords(h: int, w: int) -> Tensor:
    """[H * W, 2] (u, v) of the pixel centres, row-major, in (-1, 1) (see the module doc)."""
    u = (torch.arange(w, dtype=torch.float32) + 0.5) * (2.0 / w) - 1.0
    v = (torch.arange(h, dtype=torch.float32) + 0.5) * (2.0 / h) - 1.0
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu.reshape(-1), vv.reshape(-1)], dim=-1)


class FourierMLP(nn.Module):
    """gamma(u, v) with L frequencies -> ReLU MLP -> sigmoid RGB."""

    def __init__(self, freqs: int, hidden: int = 256, layers: int = 4) -> None:
        super().__init__()
        self.freqs = freqs
        sizes = [encoded_size(2, freqs), *[hidden] * (layers - 1), 3]
        mods: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            mods += [nn.Linear(a, b)] + ([nn.ReLU(inplace=True)] if i < len(sizes) - 2 else [])
        self.mlp = nn.Sequential(*mods)

    def forward(self, uv: Tensor) -> Tensor:  # uv [N, 2] -> rgb [N, 3]
        return torch.sigmoid(self.mlp(positional_encoding(uv, self.freqs)))

    def param_groups(self, lr: float) -> list[dict]:
        return [{"params": list(self.parameters()), "lr": lr}]


class GridImage(nn.Module):
    """The fast field (TensoRF) on the plane z = 0, colour only, no view dependence."""

    def __init__(self, resolution: int) -> None:
        super().__init__()
        self.field = TensoRF(
            aabb=[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]],
            resolution=resolution,
            density_rank=1,
            app_rank=GRID_RANK,
            view_dependent=False,
        )
        # Density is never queried: leave its factors out of the optimizer and the parameter count.
        self.field.density_planes.requires_grad_(False)  # ParameterList: each plane
        self.field.density_lines.requires_grad_(False)

    def forward(self, uv: Tensor) -> Tensor:  # uv [N, 2] -> rgb [N, 3]
        return self.field.color(torch.cat([uv, torch.zeros_like(uv[:, :1])], dim=-1), None)

    def param_groups(self, lr: float) -> list[dict]:
        return [{**g, "params": [p for p in g["params"] if p.requires_grad]} for g in self.field.param_groups(lr)]


def parameters(model: nn.Module) -> int:
    """Parameters the image depends on (of the grid's xz / yz planes and z line only what z = 0 reads)."""
    if isinstance(model, GridImage):
        f, r = model.field, model.field.resolution
        rows = 1 if r % 2 else 2  # z = 0 falls on one row (odd R) or between two (even R)
        grid = f.app_rank[0] * (r * (r + 2 * rows) + 2 * r + rows)  # planes xy, xz, yz; lines x, y, z (one rank)
        return grid + sum(p.numel() for p in (*f.basis.parameters(), *f.mlp.parameters()))
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
