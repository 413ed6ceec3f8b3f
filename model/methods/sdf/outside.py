"""What lies outside the signed distance's box in a contracted scene (a real capture that sees its surroundings):
a density field in contracted space, sampled along each ray in front of the box and behind it (neus-facto's and
BakedSDF's split: the surface inside the object's box, a NeRF for the rest).

Each ray gets two pieces of intervals around its segment in the box [t_in, t_out] (`split`):
- **front**: `front` equal intervals of [near, t_in] (empty where the ray starts in the box);
- **back**: `back` intervals from t_out on, equal steps in disparity t_out / t, out to FAR_RATIO x t_out, past which
  the run's background colour stands for what is left.
A ray that misses the box is split where it is as far from the camera as the box's centre (t_in = t_out = |o - c|,
at least near), so that its back piece starts at the scene's scale and not at the camera.

The field (a `radiance.fields.TensoRF` on the contracted cube [-2, 2]^3, `radiance.contraction`) gives a density
per unit of contracted length; an interval's optical depth is that density times the interval's contracted chord
(the density method's convention, `radiance.contraction.contraction_chord_scale`), read at a point of the interval
(jittered while training, its middle otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nerfpipe.radiance.aabb import ray_aabb_intersect
from nerfpipe.radiance.contraction import CONTRACTED_BOX, Contraction
from nerfpipe.radiance.fields import TensoRF

__all__ = ["Outside", "Piece", "split", "FRONT", "BACK", "RESOLUTION", "FAR_RATIO"]

FRONT = 8
"""Intervals between the ray's start and the box by default."""
BACK = 24
"""Intervals behind the box by default."""
RESOLUTION = 96
"""The outside field's grid resolution per axis over the contracted cube (fixed: no coarse-to-fine)."""
RANK = (8, 16)
"""The outside field's density and appearance ranks (TensoRF's 16, 48 halved and thirded: the surroundings are
seen at lower resolution than the object)."""
FAR_RATIO = 100.0
"""The back piece ends at this many times the distance where it starts."""


@dataclass(frozen=True)
class Piece:
    """Intervals of a ray batch outside the box: optical depth tau [R, K], the distance t [R, K] and the contracted
    point x [R, K, 3] where each is read."""

    tau: Tensor
    t: Tensor
    x: Tensor


def split(o: Tensor, d: Tensor, box: Tensor, near: float) -> tuple[Tensor, Tensor]:
    """Rays o, d [R, 3], the box [2, 3], the rays' start `near` -> (t_in [R], t_out [R]): the ray's segment in the
    box within [near, inf), or for a ray that misses it t_in = t_out = max(|o - centre|, near) (module doc)."""
    t0, t1, hit = ray_aabb_intersect(o, d, box)
    miss = torch.linalg.vector_norm(o - box.mean(0), dim=-1).clamp(min=near)
    t_in = torch.where(hit, t0.clamp(min=near), miss)
    t_out = torch.where(hit, torch.maximum(t1, t_in), miss)
    return t_in, t_out


@dataclass(eq=False)
class Outside:
    """The density field outside the box of a contracted scene (module doc)."""

    field: TensoRF
    contraction: Contraction
    front: int = FRONT
    back: int = BACK

    @classmethod
    def create(cls, contraction: Contraction, *, front: int = FRONT, back: int = BACK) -> Outside:
        field = TensoRF(
            aabb=torch.tensor(CONTRACTED_BOX), resolution=RESOLUTION, density_rank=RANK[0], app_rank=RANK[1]
        )
        return cls(field=field, contraction=contraction, front=front, back=back)

    def to(self, device: torch.device) -> Outside:
        self.field.to(device)
        return self

    def config(self) -> dict:
        return {"field": self.field.config(), "front": self.front, "back": self.back}

    @classmethod
    def from_config(cls, config: dict, contraction: Contraction) -> Outside:
        field = {k: v for k, v in config["field"].items() if k != "kind"}  # TensoRF.config names its kind
        return cls(field=TensoRF(**field), contraction=contraction, front=config["front"], back=config["back"])

    def pieces(
        self, o: Tensor, d: Tensor, t_in: Tensor, t_out: Tensor, near: float, *, train: bool
    ) -> tuple[Piece, Piece]:
        """(front, back) pieces of rays o, d [R, 3] around their segments [t_in, t_out] [R] (module doc)."""
        k = torch.arange(self.front + 1, dtype=o.dtype, device=o.device) / self.front  # [F + 1]
        start = torch.full_like(t_in, near).minimum(t_in)
        front = start[:, None] + k * (t_in - start)[:, None]  # [R, F + 1]
        k = torch.arange(self.back + 1, dtype=o.dtype, device=o.device) / self.back  # [B + 1]
        back = t_out[:, None] / (1 - k * (1 - 1 / FAR_RATIO))  # [R, B + 1], disparity steps
        return self._piece(o, d, front, train), self._piece(o, d, back, train)

    def _piece(self, o: Tensor, d: Tensor, ends: Tensor, train: bool) -> Piece:
        r, k = ends.shape[0], ends.shape[1] - 1
        a, b = ends[:, :-1], ends[:, 1:]  # [R, K]
        at = torch.rand_like(a) if train else torch.full_like(a, 0.5)
        t = a + at * (b - a)  # [R, K]
        c = self.contraction
        ends_c = c.contract((o[:, None, :] + d[:, None, :] * ends[..., None]).reshape(-1, 3)).reshape(r, k + 1, 3)
        chord = torch.linalg.vector_norm(ends_c[:, 1:] - ends_c[:, :-1], dim=-1)  # [R, K] contracted length
        x = c.contract((o[:, None, :] + d[:, None, :] * t[..., None]).reshape(-1, 3))  # [R K, 3]
        sigma = self.field.density(x) if train else self.field.density_inference(x)
        return Piece(tau=sigma.reshape(r, k) * chord, t=t, x=x.reshape(r, k, 3))

    def colour(self, x: Tensor, d: Tensor) -> Tensor:
        """Contracted points x [N, 3], unit directions d [N, 3] -> rgb [N, 3]."""
        return self.field.color(x, d)

    def param_groups(self, lr: float) -> list[dict]:
        return self.field.param_groups(lr)

    def describe(self) -> dict:
        return {
            "kind": "density field in contracted space",
            "resolution": self.field.resolution,
            "rank": [sum(self.field.density_rank), sum(self.field.app_rank)],
            "front_intervals": self.front,
            "back_intervals": self.back,
            "back_reaches": f"{FAR_RATIO:g} x where it starts",
        }
