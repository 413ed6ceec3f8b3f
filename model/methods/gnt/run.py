"""A gnt run for the stages (`model.run.Run`): capability rays only. Its sources are the scene's training photos
at the run's downscale, read again when the run is opened (weights plus a scene: nothing per-scene is learned but
the network, and a zero-shot run learned nothing). It gives no density, distance or colour at points: `mesh`,
`export-points` and `splat` say so in one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import torch
from torch import Tensor

from nerfpipe.data.transforms import Scene
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.device import rays_per_chunk, render_in_chunks
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
        render = partial(self.model.render, background=self.background, train=False)
        return render_in_chunks(render, rays_o, rays_d, self.chunk, self.device, median=median)
