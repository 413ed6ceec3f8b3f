"""checkpoint.pt: what a trained run saves, and the one reader of it.

The file holds tensors and primitive containers only, so it loads with `torch.load(weights_only=True)`:
format, field_config (the field's constructor arguments), field (state dict), occupancy (state dict or None),
ndc (`radiance.ndc.NDC.to_dict()` or None), optimizer (state dict), step, seconds, lr_factor, rng.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from data.atomic import atomic_path
from data.errors import UserError

__all__ = ["CHECKPOINT_FORMAT", "save_checkpoint", "read_checkpoint"]

CHECKPOINT_FORMAT = 1


def save_checkpoint(
    path: Path, model: Any, opt: torch.optim.Optimizer, step: int, seconds: float, lr_factor: float, rng: Tensor
) -> None:
    """Write `model` (a `model.field_model.FieldModel`) and the optimiser state atomically to `path`."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "field_config": model.field.config(),
        "field": model.field.state_dict(),
        "occupancy": model.grid.state_dict() if model.grid is not None else None,
        "ndc": model.ndc.to_dict() if model.ndc is not None else None,
        "optimizer": opt.state_dict(),
        "step": step,
        "seconds": seconds,
        "lr_factor": lr_factor,
        "rng": rng,
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def read_checkpoint(path: Path, device: torch.device | str) -> dict:
    """The checkpoint's dict on `device`; UserError when missing, unreadable or not ours."""
    if not path.is_file():
        raise UserError(f"{path}: no checkpoint to resume from")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # corrupt or foreign file
        raise UserError(f"{path}: cannot read checkpoint ({type(exc).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: not a nerfpipe train checkpoint (format {CHECKPOINT_FORMAT})")
    return state
