"""GNT's options group (`train --method gnt`). A field whose default is None is an automatic default
(`model.methods.gnt.GntMethod.prepare` resolves it and says why; config.json records the result)."""

from __future__ import annotations

from dataclasses import dataclass

from nerfpipe.data.errors import UserError
from nerfpipe.model.methods.gnt.features import EXTRACTORS
from nerfpipe.model.methods.gnt.net import READOUTS

__all__ = ["GntOptions", "validate_options", "SOURCE_VIEWS", "SAMPLES", "SOURCE_SIDE", "VIEWS_PER_STEP"]

SOURCE_VIEWS = 8
"""Source views a ray reads by default (GNT trains with 8 to 10)."""
SAMPLES = 32
"""Samples a ray by default on the CPU (64 on CUDA: GNT's 64 coarse samples)."""
SOURCE_SIDE = (256, 512)
"""Longest side of the source images the features are made from: CPU, CUDA."""
VIEWS_PER_STEP = 2
"""Target photos a training step draws its rays from (their sources' features are recomputed each step)."""


@dataclass(frozen=True, kw_only=True)
class GntOptions:
    """A generalizable NeRF transformer: features of the nearest photos along each ray, view and ray transformers."""

    init: str | None = None
    """Start from weights: 'pretrained' (the model shipped with nerfpipe, trained on generated scenes:
    `make pretrain-gnt`), a weights file, or another gnt run's checkpoint.pt. None: random weights. With
    --max-steps 0 the run is the weights plus the scene (zero-shot); with steps it fine-tunes them."""
    extractor: str | None = None
    """Image features: shallow (three convolutions) or resunet (a residual encoder-decoder). None: shallow, or the
    initial weights' kind."""
    readout: str | None = None
    """A sample's colour: blend (the source pixels' colours weighted by the network, IBRNet's read-out) or direct
    (the network's own colour, GNT's). None: blend, or the initial weights' kind."""
    source_views: int | None = None
    """Source photos each ray reads (the nearest in viewing angle). None: 8, or every training photo when there are
    fewer (a training ray never reads its own photo: one fewer then)."""
    gnt_samples: int | None = None
    """Samples a ray (uniform in depth through an object's box, in inverse depth otherwise). None: 32 on CPU, 64 on
    CUDA."""
    source_side: int | None = None
    """Longest side, in pixels, of the source images the features come from. None: 256 on CPU, 512 on CUDA (or
    the training images' size when smaller)."""
    views_per_step: int = VIEWS_PER_STEP
    """Training photos a step draws its rays from (GNT: one): the features of their sources are recomputed with
    gradients every step, so fewer views make a step cheaper."""


def validate_options(options: GntOptions) -> None:
    """Every check the options alone allow (UserError naming the option)."""
    if options.extractor is not None and options.extractor not in EXTRACTORS:
        raise UserError(f"extractor: expected one of {', '.join(sorted(EXTRACTORS))}, got {options.extractor!r}")
    if options.readout is not None and options.readout not in READOUTS:
        raise UserError(f"readout: expected one of {', '.join(READOUTS)}, got {options.readout!r}")
    if options.source_views is not None and options.source_views < 1:
        raise UserError(f"source_views: expected >= 1, got {options.source_views}")
    if options.gnt_samples is not None and options.gnt_samples < 2:
        raise UserError(f"gnt_samples: expected >= 2, got {options.gnt_samples}")
    if options.source_side is not None and options.source_side < 8:
        raise UserError(f"source_side: expected >= 8 pixels, got {options.source_side}")
    if options.views_per_step < 1:
        raise UserError(f"views_per_step: expected >= 1, got {options.views_per_step}")
