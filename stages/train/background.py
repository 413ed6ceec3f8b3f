"""What empty space shows in training and evaluation (`Config.background`; the rule is in
`stages.train.defaults`' module doc): the mode asked for, or with auto the images' alpha, or a plain border colour
(the 2-pixel frame of every training view), or a random colour per ray.
"""

from __future__ import annotations

import numpy as np
import torch

from nerfpipe.model.background import Background
from nerfpipe.model.views import Views

__all__ = [
    "background_conflict",
    "choose_background",
    "detect_plain_colour",
    "BORDER",
    "PLAIN_FRACTION",
    "PLAIN_TOLERANCE",
]

BORDER = 2
PLAIN_FRACTION = 0.9
PLAIN_TOLERANCE = 4 / 255
CONFLICT = 0.1
"""An asked-for background colour further than this (in any channel, 0..1) from the photos' plain border colour
contradicts them (`background_conflict`)."""


def _border_rgb(views: Views) -> np.ndarray:
    """float64 [K, 3] in [0, 1]: the colours of the 2-pixel frame of every view."""
    parts, start = [], 0
    for h, w in views.shapes:
        img = views.rgba[start : start + h * w].reshape(h, w, 4)
        start += h * w
        b = min(BORDER, h // 2, w // 2)
        mask = torch.zeros(h, w, dtype=torch.bool)
        mask[:b], mask[-b:], mask[:, :b], mask[:, -b:] = True, True, True, True
        parts.append(img[mask].numpy())
    rgba = np.concatenate(parts) if parts else np.zeros((0, 4), np.uint8)
    return rgba[:, :3].astype(np.float64) / 255.0


def detect_plain_colour(rgb: np.ndarray) -> tuple[tuple[float, float, float] | None, float]:
    """Border pixels rgb [K, 3] in [0, 1] -> (their plain colour or None, fraction within tolerance of it)."""
    if rgb.shape[0] == 0:
        return None, 0.0
    median = np.median(rgb, axis=0)
    close = (np.abs(rgb - median) <= PLAIN_TOLERANCE + 1e-9).all(axis=1)
    frac = float(close.mean())
    if frac < PLAIN_FRACTION:
        return None, frac
    colour = rgb[close].mean(axis=0)
    return (float(colour[0]), float(colour[1]), float(colour[2])), frac


def choose_background(mode: str, views: Views, has_alpha: bool) -> tuple[Background, bool, str]:
    """(the background for `Config.background` = mode, whether empty space is one plain colour, why)."""
    if mode == "black":
        return Background("fixed", (0.0, 0.0, 0.0)), True, "asked for: black"
    if mode == "white":
        return Background("fixed", (1.0, 1.0, 1.0)), True, "asked for: white"
    if mode == "random":
        return Background("random"), has_alpha, "asked for: random per ray in training, white for evaluation"
    border = _border_rgb(views)
    start = tuple(float(v) for v in np.median(border, axis=0)) if border.size else (0.5, 0.5, 0.5)
    if mode == "learned":
        return Background("learned", start), False, "asked for: a learned colour (starts at the border median)"
    if has_alpha:
        return Background("random"), True, "images have alpha: random per ray in training, white for evaluation"
    colour, frac = detect_plain_colour(border)
    if colour is not None:
        rgb = ", ".join(f"{c:.3f}" for c in colour)
        why = (
            f"{frac:.1%} of border pixels are one colour ({rgb}): its pixels train as transparent (random "
            "colour behind them), the others on that colour, as the images were made"
        )
        return Background("plain", colour), True, why
    why = f"no plain border colour ({frac:.1%}): random per ray in training (the field must explain every pixel)"
    return Background("random", start), False, why + ", the border median at evaluation"


def background_conflict(mode: str, views: Views, has_alpha: bool) -> str | None:
    """One line where an asked-for background contradicts opaque photos with a plain border colour (None where it
    does not, or where the mode was not asked for): empty space composited on black (or random colours) while the
    photos show white behind the object can only be fitted by painting the backdrop as density, or not at all
    (`make demo`'s photos with `--background black`: 2.0 dB after 400 steps, an empty field)."""
    if mode not in ("black", "white", "random") or has_alpha:
        return None
    colour, frac = detect_plain_colour(_border_rgb(views))
    if colour is None:
        return None
    asked = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}.get(mode)
    if asked is not None and max(abs(a - c) for a, c in zip(asked, colour, strict=True)) <= CONFLICT:
        return None
    rgb = ", ".join(f"{c:.2f}" for c in colour)
    behind = "random colours" if asked is None else mode
    return (
        f"the photos' border is one colour ({rgb}) in {frac:.0%} of its pixels, but training put {behind} behind "
        "empty space (--background " + mode + ")"
    )
