"""render's time budget: the render speed measured on a few small views of the path, and the frame size and count that
fit what is left of the budget (`fit_budget`); the depth range a depth video is coloured over."""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from nerfpipe.model import OPAQUE, CameraPath, Run, render_view

__all__ = [
    "MIN_SHORT_SIDE",
    "MIN_FRAMES",
    "MIN_FPS",
    "PREVIEW_RAYS",
    "PREVIEW_VIEWS",
    "depth_range",
    "rays_per_second",
    "fit_budget",
]


MIN_SHORT_SIDE = 240
"""A time budget shrinks frames down to this many pixels on their short side (never up) before dropping frames."""


MIN_FRAMES = 24
"""A time budget keeps at least this many frames of a synthetic path (fewer only when fewer were asked for)."""


MIN_FPS = 8.0
"""When a time budget drops frames, the frame rate drops with them (the video keeps the length asked for, as a
slower sequence: 25 of 120 frames at 30 fps would last under a second) but not below this."""


PREVIEW_RAYS = 16384
"""Pixels per preview view for the rays/s measurement (two chunks of the fast field)."""


PREVIEW_VIEWS = 3


def depth_range(trained: Run, cams: CameraPath, device: torch.device, scale: float) -> tuple[float, float]:
    """1st-99th percentile of opaque z-depth (user units) over a 1/8-resolution preview of up to 16 frames."""
    picks = np.unique(np.linspace(0, len(cams.names) - 1, min(16, len(cams.names))).round().astype(int))
    vals = []
    for k in picks:
        intr = cams.intrinsics[k]
        small = intr.scaled(max(8 / min(intr.w, intr.h), 1 / 8)) if min(intr.w, intr.h) > 8 else intr
        view = render_view(trained, small, cams.world_from_cams[k], device)
        vals.append(view["depth"][view["acc"] >= OPAQUE] / scale)
    v = np.concatenate(vals) if vals else np.zeros(0)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(v, [1, 99]))
    return (lo, hi) if hi > lo else (lo, lo + 1e-6 + abs(lo) * 1e-3)


def rays_per_second(trained: Run, cams: CameraPath, device: torch.device, infer=None) -> tuple[float, int, float]:
    """Measured on `PREVIEW_VIEWS` cameras spread along the path, each scaled to about `PREVIEW_RAYS` pixels,
    after one untimed tiny render (warm-up), at the video's inference settings `infer` (None: the run's default).
    Returns (rays/s, rays rendered, seconds)."""
    n = len(cams.names)
    picks = np.unique(np.linspace(0, n - 1, min(PREVIEW_VIEWS, n)).round().astype(int))
    tiny = cams.intrinsics[0].scaled(min(1.0, 8 / max(cams.intrinsics[0].w, cams.intrinsics[0].h)))
    render_view(trained, tiny, cams.world_from_cams[0], device, infer=infer)
    rays, seconds = 0, 0.0
    for k in picks:
        intr = cams.intrinsics[k]
        small = intr.scaled(min(1.0, math.sqrt(PREVIEW_RAYS / (intr.w * intr.h))))
        t0 = time.perf_counter()
        render_view(trained, small, cams.world_from_cams[k], device, infer=infer)
        seconds += time.perf_counter() - t0
        rays += small.w * small.h
    return rays / max(seconds, 1e-9), rays, seconds


def fit_budget(
    *,
    seconds: float,
    rays_per_s: float,
    rays_per_frame: float,
    frames: int,
    short_side: int,
    drop_frames: bool,
) -> tuple[float, int, str]:
    """What fits in `seconds` at `rays_per_s`: (linear image scale <= 1, frames, reason).

    The image shrinks first, to the scale that fits but not below `MIN_SHORT_SIDE` pixels on its short side;
    then (when `drop_frames`) frames go, down to `MIN_FRAMES` (or `frames` if fewer were asked for). What still
    does not fit is rendered anyway, and the reason says so.
    """
    if not seconds > 0 or not rays_per_s > 0:
        raise ValueError(f"expected seconds > 0 and rays_per_s > 0, got {seconds}, {rays_per_s}")
    need = frames * rays_per_frame / rays_per_s
    if need <= seconds:
        return 1.0, frames, f"fits: about {need:.0f} s for {seconds:.0f} s"
    floor = min(1.0, MIN_SHORT_SIDE / max(short_side, 1))
    scale = max(math.sqrt(seconds / need), floor)
    per_frame = rays_per_frame * scale * scale / rays_per_s
    keep = frames
    if drop_frames and per_frame * frames > seconds * (1 + 1e-9):
        keep = max(min(frames, MIN_FRAMES), min(frames, int(seconds / per_frame)))
    shrunk = f"about {need:.0f} s asked for, {seconds:.0f} s budget"
    if scale == 1:
        how = f"size kept (short side {short_side} px <= {MIN_SHORT_SIDE})"
    else:
        how = f"images scaled by {scale:.3g}" + (f" (short side floor {MIN_SHORT_SIDE} px)" if scale == floor else "")
    if keep < frames:
        how += f", {keep} of {frames} frames"
    over = per_frame * keep - seconds
    tail = f"; still about {over:.0f} s over (floors reached)" if over > 0.05 * seconds else ""
    return scale, keep, f"{shrunk}: {how}{tail}"
