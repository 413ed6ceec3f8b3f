"""A run's Gaussian splats in the browser, beside the field's render: viser draws them itself (WebGL, sorted in the
browser), so moving the camera is real time however slow the server renders the field.

Which splat file: `Config.splats` when given (it must have been made from the run viewed: its report names that
run), else `RUN_DIR/SPLATS_NAME` when that file exists (a splat file found there that is not usable is skipped with
a warning line; a given one that is not usable is a UserError). The Gaussians are mapped back to the run's scene
frame (the viewer's world, `stages.view.cameras`) by the inverse of the report's `out_from_scene`
(`model.splat_run`), and sent as viser's `add_gaussian_splats(name, centers [N, 3], covariances [N, 3, 3],
rgbs [N, 3], opacities [N, 1])`: covariance R S S R^T, colour 0.5 + SH_C0 f_dc clipped to [0, 1] (viser's splats
have no view-dependent colour: higher SH degrees are left out), opacity sigmoid(logit).

A dropdown (`Draw`, in the Render folder) switches between the splats (the field's live render paused and the
background image cleared) and the field (the splats hidden, the live render resumed); splats are shown first.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.model.splat_run import RenderInput, open_input
from nerfpipe.radiance import splats as sp

__all__ = ["SPLATS_NAME", "NODE", "DRAW", "find_splats", "viser_arrays", "SplatLayer"]

SPLATS_NAME = "splats.ply"
"""A splat file of this name in the run folder is shown without `Config.splats`."""
NODE = "/splats"
"""The scene node holding the Gaussians."""
DRAW = ("splats", "field")
"""The `Draw` dropdown's choices: the splats (drawn by the browser) or the field (rendered by the server)."""


def find_splats(run_dir: Path, given: Path | None) -> RenderInput | None:
    """The splat file to show for the run `run_dir` (module doc), or None."""
    path = Path(given) if given is not None else Path(run_dir) / SPLATS_NAME
    if given is None and not path.is_file():
        return None
    try:
        source = open_input(path)
        if source.splat_file is None:
            raise UserError(f"{path}: splats: expected a splat .ply made by the splat stage, got a folder")
        if not os.path.samefile(source.run_dir, run_dir):
            raise UserError(
                f"{path}: made from the run {source.run_dir}, not {run_dir}; expected splats of the run viewed"
            )
        return source
    except UserError as exc:
        if given is not None:
            raise
        print(f"warning: view: {exc} (not shown)", file=sys.stderr)
        return None


def viser_arrays(splats: sp.Splats) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gaussians (scene frame) -> float32 centers [N, 3], covariances [N, 3, 3], rgbs [N, 3], opacities [N, 1]."""
    with torch.no_grad():
        cov = sp.covariance(splats.log_scales, splats.quats)
        rgb = (0.5 + sp.SH_C0 * splats.sh[:, 0]).clamp(0.0, 1.0)
        opacity = torch.sigmoid(splats.opacity_logits)[:, None]
    return tuple(
        np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32) for t in (splats.means, cov, rgb, opacity)
    )


@dataclass
class SplatLayer:
    """The splat node and its `Draw` dropdown over a run viewer's live render (`stages.view.run_view.LiveRender`)."""

    handle: object
    """viser's GaussianSplatHandle."""
    draw: object
    """The dropdown."""
    source: RenderInput
    count: int

    @classmethod
    def add(cls, server, source: RenderInput, live) -> SplatLayer:
        """Draw the splats of `source` and the dropdown (call inside the GUI folder it belongs to)."""
        splats = source.read_splats()
        handle = server.scene.add_gaussian_splats(NODE, *viser_arrays(splats))
        draw = server.gui.add_dropdown("Draw", DRAW, initial_value="splats")
        server.gui.add_markdown(f"{len(splats)} Gaussians from `{source.splat_file.name}`: drawn by the browser")
        layer = cls(handle=handle, draw=draw, source=source, count=len(splats))
        live.set_paused(True)

        @draw.on_update
        def _(_event) -> None:
            layer.show(draw.value, live)

        return layer

    def show(self, what: str, live) -> None:
        """`splats`: the node visible, the live render paused; `field`: the node hidden, the live render on."""
        if what not in DRAW:
            raise ValueError(f"expected one of {DRAW}, got {what!r}")
        self.handle.visible = what == "splats"
        live.set_paused(what == "splats")
