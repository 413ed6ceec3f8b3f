"""The splat stage's optimisation (`stages.splat`): its settings, the step on the shared training loop
(`model.loop`), the scoring of the training views and the report's entries about them."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.progress import Progress
from nerfpipe.data.rundir import MetricsLog
from nerfpipe.model import splat_density
from nerfpipe.model.loop import Clock
from nerfpipe.model.splat_backends import Backend
from nerfpipe.model.splat_views import TrainingPhotos
from nerfpipe.radiance import splats as sp
from nerfpipe.radiance.metrics import psnr_from_mse

__all__ = [
    "LRS",
    "LR_DECAY",
    "SH_REST_LR",
    "SH_AT",
    "DENSIFY_EVERY",
    "DENSIFY_SPAN",
    "DENSIFY_LIMIT",
    "DENSIFY_OFF",
    "EVAL_VIEWS",
    "Steps",
    "shown_splats",
    "score",
    "extent_of",
    "densification",
    "colour_left_out",
]

LRS = {"means": 1.6e-4, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh": 2.5e-3}
"""Adam learning rates per parameter (3DGS's; means' times the scene extent)."""
LR_DECAY = 0.1
SH_REST_LR = 1.0
"""The higher SH coefficients learn at this times the colour's rate. 3DGS uses 1/20 over 30k steps; our CPU budget
gives ~3k steps, and on lego_400 (300 s, field 33.78 dB) 1/20, 1/5, 1/2 and 1 scored 32.03, 32.58, 32.99 and 33.11
dB held-out: the bands need the full rate to settle in so few steps. The optimiser holds them divided by it
(`shown_splats` multiplies back), so one [N, K, 3] tensor keeps every coefficient of a Gaussian in its row
(densification copies rows) while Adam, whose step does not depend on the gradient's scale, moves them at that rate;
a longer (GPU) budget may want 3DGS's 1/20, unmeasured here."""
SH_AT = (0.1, 0.2, 0.3)
"""Run progress at which the colours' SH degree rises to 1, 2, 3 (3DGS: one band every 1000 of 30k steps, so that
the view-independent colour settles first); bands above `Config.sh_degree` are never used."""
DENSIFY_EVERY = 100
"""Steps between two densifications (3DGS)."""
DENSIFY_SPAN = (0.1, 0.6)
"""Densify while the run's progress (the larger of its step and time fractions) is in this span."""
DENSIFY_LIMIT = 2.0
"""Densification stops growing at this many times the initial Gaussians (each step's time grows with them)."""
DENSIFY_OFF = (
    "off by default (--densify): a fixed count; measured within noise in 300 s on CPU (fox +0.13 dB, "
    "lego_400 -0.20 dB at 50k Gaussians)"
)
"""What the report's left_out says when densification is off."""
EVAL_VIEWS = 8
"""Training views (evenly spaced) scored before and after the optimisation."""


def _psnr(a: Tensor, b: Tensor) -> float:
    return psnr_from_mse(float(torch.mean((a.detach().float() - b.float()) ** 2)))


@dataclass(kw_only=True)
class Steps:
    """The splat step on the shared loop (`model.loop.Stepper`; no checkpoints: the output is written at the end)."""

    splats: sp.Splats
    opt: torch.optim.Optimizer
    views: TrainingPhotos
    backend: Backend
    background: Tensor
    gen: torch.Generator
    clock: Clock
    metrics: MetricsLog
    progress: Progress
    task: Any
    extent: float
    limit: int
    """Most Gaussians densification may reach."""
    densify: bool
    sh_degree: int
    """The highest SH degree the run reaches (`Config.sh_degree`)."""
    step: int = 0
    lr_factor: float = 1.0
    degree: int = 0
    """The SH degree in use now (raised at SH_AT)."""
    last: dict = field(default_factory=dict)
    stats: splat_density.GradStats = field(init=False)
    refined_at: int = -1
    refinements: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.stats = splat_density.GradStats.zeros(len(self.splats), self.splats.means.device)

    def prepare(self, fraction: float) -> bool:
        """Densification (`model.splat_density.refine`) every DENSIFY_EVERY steps while the run's fraction is in
        DENSIFY_SPAN; True when the Gaussians were replaced. The SH degree in use follows the run's fraction (SH_AT)."""
        self.degree = min(self.sh_degree, sum(fraction >= f for f in SH_AT))
        if not (
            self.densify
            and self.step > 0
            and self.step % DENSIFY_EVERY == 0
            and self.step != self.refined_at
            and DENSIFY_SPAN[0] <= fraction < DENSIFY_SPAN[1]
        ):
            return False
        self.refined_at = self.step
        new, source, fresh, counts = splat_density.refine(
            self.splats, self.stats, extent=self.extent, limit=self.limit, gen=self.gen
        )
        self._replace([p.requires_grad_(True) for p in new.parameters()], source, fresh)
        self.refinements.append({"step": self.step, **counts})
        return True

    def _replace(self, params: list[Tensor], source: Tensor | None = None, fresh: Tensor | None = None) -> None:
        """New Gaussians in place of the current ones: the optimiser's moments follow `source` rows (densification),
        or are dropped (a restore loads its own)."""
        old = self.splats.parameters()
        if source is not None:
            splat_density.carry_adam(self.opt, old, params, source, fresh)
        else:
            splat_density.swap_parameters(self.opt, old, params)
        self.splats = sp.Splats(*params)
        self.stats = splat_density.GradStats.zeros(len(self.splats), params[0].device)

    def train_step(self, lr: float) -> bool:
        k = int(torch.randint(len(self.views.photos), (1,), generator=self.gen))
        device = self.splats.means.device
        target = self.views.target(k, device)
        intr = self.views.intrinsics[k]
        shown = shown_splats(self.splats, self.degree)
        rgb, means2d, visible = self.backend.render(shown, self.views.world_from_cams[k], intr, self.background)
        err = torch.mean(torch.abs(rgb - target))
        loss = float(err.detach())
        if not math.isfinite(loss):
            return False
        self.opt.zero_grad(set_to_none=True)
        err.backward()
        self.opt.step()
        if self.densify and means2d.grad is not None:
            self.stats.add(means2d.grad.reshape(-1, 2), visible, intr.w, intr.h)
        self.last = {"loss": loss, "psnr": _psnr(rgb, target)}
        return True

    def log(self, lr: float) -> None:
        self.metrics.append(
            step=self.step,
            seconds=round(self.clock(), 4),
            loss=round(self.last["loss"], 6),
            psnr=round(self.last["psnr"], 4),
        )
        self.progress.advance(self.task)

    def snapshot(self) -> tuple[list[Tensor], dict]:
        return [p.detach().clone() for p in self.splats.parameters()], copy.deepcopy(self.opt.state_dict())

    def restore(self, snapshot: tuple[list[Tensor], dict]) -> None:
        """The snapshot's Gaussians (their count may differ from now's: densification) and optimiser state."""
        self._replace([p.clone().requires_grad_(True) for p in snapshot[0]])
        self.opt.load_state_dict(snapshot[1])

    def checkpoint(self, seconds: float) -> None:
        pass

    def finish(self, seconds: float) -> None:
        pass


def shown_splats(splats: sp.Splats, degree: int | None = None) -> sp.Splats:
    """The Gaussians the rasteriser sees: the optimiser's (SH_REST_LR: higher coefficients held / SH_REST_LR) with
    the SH bands up to `degree` (None: all it holds)."""
    k = splats.sh.shape[1] if degree is None else (degree + 1) ** 2
    scale = torch.full((k, 1), SH_REST_LR, dtype=splats.sh.dtype, device=splats.sh.device)
    scale[0] = 1.0
    return sp.Splats(splats.means, splats.log_scales, splats.quats, splats.opacity_logits, splats.sh[:, :k] * scale)


def colour_left_out(sh_degree: int, fmt: str) -> dict[str, str]:
    """The report's `left_out` entry for view-dependent colour: none asked for, or a file layout that drops it."""
    if not sh_degree:
        return {"view_dependent_colour": "SH degree 0 (--sh-degree 0)"}
    if fmt == "splat":
        return {"view_dependent_colour": f"optimised to degree {sh_degree}; the .splat layout holds degree 0 only"}
    return {}


@torch.no_grad()
def score(splats: sp.Splats, views: TrainingPhotos, backend: Backend, background: Tensor, picks: list[int]) -> float:
    device = splats.means.device
    shown = shown_splats(splats)
    return float(
        np.mean(
            [
                _psnr(
                    backend.render(shown, views.world_from_cams[k], views.intrinsics[k], background)[0],
                    views.target(k, device),
                )
                for k in picks
            ]
        )
    )


def extent_of(views: TrainingPhotos) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera centre from their mean (1 for a single view)."""
    centres = torch.stack([p[:3, 3] for p in views.world_from_cams])
    radius = float(torch.linalg.norm(centres - centres.mean(0), dim=-1).max())
    return 1.1 * radius if radius > 0 else 1.0


# ---------------------------------------------------------------------------------------------- the stage
def densification(steps: Steps, densify: bool) -> dict | str:
    if not densify:
        return "off (--densify turns it on)"
    d = splat_density
    return {
        "rule": f"every {DENSIFY_EVERY} steps while the run's progress is in {list(DENSIFY_SPAN)}: clone "
        f"(small) or split (largest scale > {d.PERCENT_DENSE} x extent) where the mean view-space "
        f"gradient > {d.GRAD_THRESHOLD}, prune opacity < {d.MIN_OPACITY}",
        "limit": steps.limit,
        "refinements": steps.refinements,
    }
