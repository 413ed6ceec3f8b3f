"""The SDF method's `TrainModel`: rays through the box, NeuS's opacity from the signed distance, colour given the
normal, composited with transmittance exp(-exclusive_cumsum(tau)) (`model.methods.sdf.neus`).

Each ray is cut into `samples` equal intervals of its segment in the signed distance's box (`SdfField.aabb`),
jittered while training. The distance at every interval's middle is read without gradient; only the intervals of
the *band* (where that distance is small enough that the interval may hold the surface: `BAND_STEPS`,
`BAND_SHARPNESS`) are differentiated, each cut into `refine` equal sub-intervals (NeuS's up-sampling near the
surface, deterministic): the distances at the sub-intervals' ends are read with gradient (NeuS's section points,
read, not estimated from a slope), and each sub-interval's opacity is NeuS's logistic ratio of them with the learned
sharpness s (`neus_tau`). Outside the band the opacity is that of a unit-slope entry (0 far outside, opaque deep
inside), without gradient, shared evenly by the interval's sub-intervals. Where a sub-interval's weight is above
`COLOR_THRESHOLD` the colour network sees, at its middle, the unit normal g / |g| (g by central differences one grid
cell wide: `SdfField.sdf_and_gradient`). A training render also returns the Eikonal residual (|g| - 1)^2 over those
samples and one free point a ray in the box (`eikonal`): the hook adds it to the loss.

In a contracted scene (a real capture) the box is the object's, and `outside` (a density field in contracted
space: `model.methods.sdf.outside`) gives intervals in front of the box and behind it; the three pieces are
composited as one ray (their optical depths concatenated in order along it), so the surroundings hide or show the
surface as they stand.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nerfpipe.model.appearance import Appearance
from nerfpipe.model.background import Background
from nerfpipe.model.field_model import param_groups
from nerfpipe.model.methods.sdf.field import SdfField
from nerfpipe.model.methods.sdf.neus import composite_weights, neus_tau, weights_from_tau
from nerfpipe.model.methods.sdf.outside import Outside, Piece, split
from nerfpipe.radiance.aabb import ray_aabb_segment
from nerfpipe.radiance.safe import eps
from nerfpipe.radiance.space import Space

__all__ = ["SdfModel", "BAND_STEPS", "BAND_SHARPNESS", "COLOR_THRESHOLD"]

BAND_STEPS = 1.0
"""The band holds samples within this many interval lengths of the surface (by their distance, no gradient)..."""
BAND_SHARPNESS = 4.0
"""... plus this many logistic widths 1 / s (where Phi_s(f) differs from 0 or 1 by more than e^-4: outside it the
unit-slope opacity is close, only its gradient is dropped) and a cell."""
COLOR_THRESHOLD = 1e-4
"""Weight above which a sample's colour is evaluated (TensoRF's rule, as the density method's)."""


@dataclass(eq=False)
class SdfModel:
    """A signed-distance field in the scene's box (module doc): a `model.methods.base.TrainModel`."""

    field: SdfField
    space: Space
    """A `Box` (an object scene) or `Contracted` (a real capture: `outside` models what lies beyond the box)."""
    samples: int
    """Intervals a ray is cut into, in training and rendering."""
    refine: int = 1
    """Sub-intervals each interval of the band is cut into (1: none)."""
    background: Background | None = None
    appearance: Appearance | None = None
    outside: Outside | None = None
    """The density field outside the box (a contracted scene: `model.methods.sdf.outside`); None: an object scene."""
    chunk: int = 1024
    random_draws_per_ray: int = 4
    """One jitter and one free point (3 numbers) a ray, and one a sample outside the box (set in __post_init__:
    data-parallel runs place a rank's draws by it)."""
    curvature: bool = False
    """Training renders also return `curvature`, mean |Laplacian f| over the coloured samples (Neuralangelo's
    curvature term, from the same six points as the normal and one more at the centre)."""
    last_eikonal: float = math.nan
    """The Eikonal residual (|g| - 1)^2 of the last training render (the manifest and the metrics)."""

    def __post_init__(self) -> None:
        self.random_draws_per_ray = 4 + (self.outside.front + self.outside.back if self.outside is not None else 0)

    def render(
        self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, view: Tensor | None = None, **_: Any
    ) -> dict[str, Tensor]:
        """World rays o, d [R, 3] (unit d) -> dict(rgb [R, 3], acc [R], depth [R], depth_median [R], samples, and
        while training eikonal (a 0-d tensor)). Keyword arguments of other models (median, infer, gen) are
        accepted and change nothing: every render here is the same quadrature."""
        out = self._render(o, d, background, train=train)
        if self.appearance is not None:
            out["rgb"] = self.appearance(out["rgb"], out["acc"], background, view)
        return out

    def _render(self, o: Tensor, d: Tensor, background: Tensor, *, train: bool) -> dict[str, Tensor]:
        field, n, m, s = self.field, self.samples, self.refine, self.field.sharpness
        box = field.aabb.to(o)
        if self.outside is None:
            t_near, t_far = ray_aabb_segment(o, d, box, self.space.near, self.space.far)  # [R] each, scene units
        else:
            t_near, t_far = split(o, d, box, self.space.near)
        frac = torch.arange(n, dtype=o.dtype, device=o.device) / n  # [S]
        r = o.shape[0]
        jitter = torch.rand(r, 1, dtype=o.dtype, device=o.device) if train else torch.full_like(t_near[:, None], 0.5)
        span = (t_far - t_near)[:, None]  # [R, 1]
        t_mid = t_near[:, None] + (frac + jitter / n) * span  # [R, S]
        delta = (span / n / field.half).expand_as(t_mid).reshape(-1)  # [R S] in u units
        u = field.to_unit(o[:, None, :] + d[:, None, :] * t_mid[..., None]).reshape(-1, 3)  # [R S, 3]
        dirs = d[:, None, :].expand(r, n, 3).reshape(-1, 3)
        with torch.no_grad():  # the band: samples whose interval may hold the surface (module doc)
            f_all = field.sdf_unit(u)  # [R S]
            near = f_all.abs() < delta * BAND_STEPS + BAND_SHARPNESS / s.detach() + field.cell
            tau = neus_tau(f_all + 0.5 * delta, f_all - 0.5 * delta, s.detach())  # elsewhere: a unit-slope entry
        band = near.nonzero()[:, 0]  # [B]
        # a band interval is cut into m sub-intervals: its m + 1 ends are read with gradient
        ends = torch.arange(m + 1, dtype=o.dtype, device=o.device) / m - 0.5  # [m + 1] of an interval
        mids = (torch.arange(m, dtype=o.dtype, device=o.device) + 0.5) / m - 0.5  # [m]
        step = delta[band, None, None] * dirs[band, None, :]  # [B, 1, 3] one interval along the ray, u units
        f_ends = field.sdf_unit((u[band, None, :] + ends[:, None] * step).reshape(-1, 3)).reshape(-1, m + 1)
        tau = (tau / m)[:, None].expand(r * n, m).index_put((band,), neus_tau(f_ends[:, :-1], f_ends[:, 1:], s))
        t_sub = (t_mid[..., None] + mids * (span / n)[..., None]).reshape(r, n * m)  # [R, S m]
        pieces: tuple[Piece, ...] = ()
        if self.outside is not None:  # a contracted scene: intervals in front of the box and behind it
            pieces = self.outside.pieces(o, d, t_near, t_far, self.space.near, train=train)
        taus = [pieces[0].tau, tau.reshape(r, n * m), pieces[1].tau] if pieces else [tau.reshape(r, n * m)]
        weights = weights_from_tau(torch.cat(taus, -1))  # [R, F + S m + B]
        first = pieces[0].tau.shape[1] if pieces else 0
        inner = weights[:, first : first + n * m]  # [R, S m]
        sub = (band[:, None] * m + torch.arange(m, device=o.device)).reshape(-1)  # [B m] band sub-intervals
        lit = sub[inner.detach().reshape(-1)[sub] > COLOR_THRESHOLD]  # worth a colour: [L]
        whole = lit.div(m, rounding_mode="floor")  # [L] their intervals
        u_lit = u[whole] + (mids[lit % m] * delta[whole])[:, None] * dirs[whole]  # [L, 3]
        f_six, g = field.sdf_and_gradient(u_lit)  # [L] the six points' mean, [L, 3]
        norm = torch.linalg.vector_norm(g, dim=-1, keepdim=True)  # [L, 1]
        rgb = torch.zeros(r * n * m, 3, dtype=o.dtype, device=o.device)
        if lit.numel():
            view = dirs[whole] if field.view_dependent else None
            rgb = rgb.index_put((lit,), field.color(u_lit, g / norm.clamp_min(eps(g.dtype)), view))
        rgbs, ts = [rgb.reshape(r, n * m, 3)], [t_sub]
        if pieces:
            back = weights[:, first + n * m :]
            rgbs = [self._outside_rgb(pieces[0], weights[:, :first], d, train), *rgbs]
            rgbs.append(self._outside_rgb(pieces[1], back, d, train))
            ts = [pieces[0].t, t_sub, pieces[1].t]
        out = composite_weights(weights, torch.cat(rgbs, 1), torch.cat(ts, -1), background)
        out["samples"] = torch.tensor(float(band.numel() * m + sum(p.tau.numel() for p in pieces)))
        if train:
            lo, hi = field.to_unit(box)
            free = lo + torch.rand(r, 3, dtype=o.dtype, device=o.device) * (hi - lo)  # one free point a ray
            _, g_free = field.sdf_and_gradient(free)
            norms = torch.cat([norm[:, 0], torch.linalg.vector_norm(g_free, dim=-1)])
            out["eikonal"] = ((norms - 1) ** 2).mean()
            self.last_eikonal = float(out["eikonal"].detach())
            if self.curvature and lit.numel():  # the six points' mean is f + h^2 lap f / 6 (field doc)
                lap = (f_six - field.sdf_unit(u_lit)) * (6.0 / field.cell**2)  # [L]
                out["curvature"] = lap.abs().mean()
        return out

    def _outside_rgb(self, piece: Piece, weights: Tensor, d: Tensor, train: bool) -> Tensor:
        """The colours [R, K, 3] of a piece outside the box whose weights [R, K] are worth one (while training,
        also each ray's largest: at the start every weight is below the threshold, and the outside field's colour
        would get no gradient)."""
        r, k = weights.shape
        w = weights.detach()
        lit = w > COLOR_THRESHOLD
        if train and k:
            lit |= w == w.amax(-1, keepdim=True)
        idx = lit.reshape(-1).nonzero()[:, 0]  # [L]
        rgb = torch.zeros(r * k, 3, dtype=d.dtype, device=d.device)
        if idx.numel():
            dirs = d[:, None, :].expand(r, k, 3).reshape(-1, 3)[idx]
            rgb = rgb.index_put((idx,), self.outside.colour(piece.x.reshape(-1, 3)[idx], dirs))
        return rgb.reshape(r, k, 3)

    # ------------------------------------------------------------------------------------------------ TrainModel
    def param_groups(self, lr: float) -> list[dict]:
        outside = self.outside.param_groups(lr) if self.outside is not None else []
        return param_groups(self.field.param_groups(lr) + outside, self.background, self.appearance, lr)

    def train_mode(self, on: bool) -> None:
        self.field.train(on)
        if self.outside is not None:
            self.outside.field.train(on)

    def after_step(self) -> None:
        if self.outside is not None:
            self.outside.field.touch()  # fused Adam leaves the version counters: its inference cache must know

    def learned(self) -> dict[str, torch.nn.Module]:
        mods = {"field": self.field, "background": self.background, "appearance": self.appearance}
        mods["outside"] = self.outside.field if self.outside is not None else None
        return {k: v for k, v in mods.items() if v is not None}

    def snapshot(self) -> dict[str, Any]:
        state = {k: copy.deepcopy(v.state_dict()) for k, v in self.learned().items()}
        return state | {"resolution": self.field.resolution}

    def restore(self, snapshot: dict[str, Any]) -> bool:
        now = self.field.resolution
        resampled = now != snapshot["resolution"]
        if resampled:
            self.field.upsample(snapshot["resolution"])
        for key, mod in self.learned().items():
            mod.load_state_dict(snapshot[key])
        if resampled:
            self.field.upsample(now)
        return resampled

    def describe(self) -> dict[str, Any]:
        """The manifest's record: the field's configuration, its sharpness now, the samples a ray, the space."""
        return {
            "field": {"kind": "sdf", **self.field.config()},
            "view_dependent": self.field.view_dependent,
            "sdf": {
                "sharpness": round(float(self.field.sharpness.detach()), 3),
                "band_in_cells": round(1.0 / (float(self.field.sharpness.detach()) * self.field.cell), 4),
                "samples_per_ray": self.samples,
                "refine": self.refine,
                "last_eikonal": round(self.last_eikonal, 5) if math.isfinite(self.last_eikonal) else None,
            },
            "scene_model": self.space.name,
            "outside": self.outside.describe() if self.outside is not None else None,
            "space": self.space.describe(),
        }
