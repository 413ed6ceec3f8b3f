"""A gnt run for the stages (`model.run.Run`): capability rays only. Its sources are the scene's training photos
at the run's downscale, read again when the run is opened (weights plus a scene: nothing per-scene is learned but
the network, and a zero-shot run learned nothing). It gives no density, distance or colour at points: `mesh`,
`export-points` and `splat` say so in one line.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nerfpipe.data.transforms import Scene
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.device import rays_per_chunk
from nerfpipe.model.methods.gnt.model import GntModel

__all__ = ["GntRun"]


@dataclass
class GntRun:
    """A gnt run, ready for rendering (no grad, chunked)."""

    scene: Scene
    model: GntModel
    device: torch.device
    background: Tensor  # [3] evaluation background
    downscale: float = 1.0
    pose_refinement: dict | None = None
    method: str = "gnt"
    capabilities: frozenset = frozenset({"rays"})

    @property
    def far(self) -> float:
        return float(self.model.range.far)

    @property
    def chunk(self) -> int:
        return rays_per_chunk(self.model.chunk, self.device)

    @property
    def appearance(self) -> Appearance | None:
        return self.model.appearance

    @torch.no_grad()
    def render_rays(self, rays_o: Tensor, rays_d: Tensor, *, infer=None, median: bool = True) -> dict[str, Tensor]:
        """rays_o, rays_d [R, 3] (unit) -> dict(rgb [R, 3], depth [R], acc [R], and with `median` depth_median [R]).
        `infer` is accepted for the stages' sake and changes nothing (no march to stop early)."""
        if rays_o.shape != rays_d.shape or rays_o.ndim != 2 or rays_o.shape[-1] != 3:
            raise ValueError(f"expected rays_o, rays_d [R, 3], got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}")
        keys = ("rgb", "depth", "depth_median", "acc") if median else ("rgb", "depth", "acc")
        parts: dict[str, list[Tensor]] = {k: [] for k in keys}
        for i in range(0, rays_o.shape[0], self.chunk):
            o = rays_o[i : i + self.chunk].to(self.device, torch.float32)
            d = rays_d[i : i + self.chunk].to(self.device, torch.float32)
            out = self.model.render(o, d, self.background, train=False)
            for k in parts:
                parts[k].append(out[k])
        return {k: torch.cat(v) if v else torch.zeros(0, device=self.device) for k, v in parts.items()}
