"""render's self-check, gathered frame by frame (`FrameWatch`): empty frames, still frames, non-finite values."""

from __future__ import annotations

import math

import numpy as np

from nerfpipe.data.checks import Check
from nerfpipe.model import OPAQUE

__all__ = ["EMPTY_ACC", "MAX_EMPTY", "STILL_DIFF", "MAX_STILL", "FrameWatch"]


EMPTY_ACC = 0.05
"""A pixel whose accumulated opacity is below this shows (almost) nothing of the field: background only."""


MAX_EMPTY = 0.95
"""Self-check: at most this share of the median frame's pixels may be empty. The test sphere (an object on a white
background at the training distance) covers a tenth of its frames; a path that misses the object covers ~0."""


STILL_DIFF = 0.5 / 255
"""Two consecutive frames whose mean absolute RGB difference is below this look the same in the 8-bit video."""


MAX_STILL = 0.9
"""Self-check: at most this share of consecutive frame pairs may look the same."""


class FrameWatch:
    """The self-check's figures (module doc), gathered frame by frame: one previous frame is kept, nothing more."""

    def __init__(self, shows_depth: bool) -> None:
        self.shows_depth = shows_depth
        self.empty: list[float] = []  # per frame: share of pixels with accumulation < EMPTY_ACC
        self.pairs = self.still = self.non_finite = 0
        self._last: np.ndarray | None = None

    def add(self, view: dict[str, np.ndarray]) -> None:
        rgb, acc = view["rgb"], view["acc"]  # [H, W, 3], [H, W]
        bad = ~np.isfinite(rgb).all(-1) | ~np.isfinite(acc)
        if self.shows_depth:
            bad |= (acc >= OPAQUE) & ~np.isfinite(view["depth"])
        self.non_finite += int(bad.sum())
        self.empty.append(float(np.mean(~(acc >= EMPTY_ACC))))  # NaN opacity counts as empty
        rgb = np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0)
        if self._last is not None and self._last.shape == rgb.shape:
            self.pairs += 1
            self.still += bool(np.abs(rgb - self._last).mean() < STILL_DIFF)
        self._last = rgb

    def checks(self) -> list[Check]:
        out = [
            Check.upper(
                "empty_frames",
                float(np.median(self.empty)) if self.empty else math.nan,
                MAX_EMPTY,
                f"the median frame shows almost nothing (accumulation < {EMPTY_ACC:g}): the camera path misses the "
                "object, or the field is empty",
            )
        ]
        if self.pairs:
            out.append(
                Check.upper(
                    "still_frames",
                    self.still / self.pairs,
                    MAX_STILL,
                    "nearly every frame repeats the one before: the camera path does not move, "
                    "or there is nothing to see",
                )
            )
        out.append(
            Check.upper(
                "non_finite",
                self.non_finite,
                0,
                "NaN or inf in the rendered colour, opacity or "
                "depth (the video shows them as black or white): the field's output is broken "
                "there",
            )
        )
        return out
