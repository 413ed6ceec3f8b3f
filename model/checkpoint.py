"""checkpoint.pt: what a trained run saves, and the one reader of it.

The file holds tensors and primitive containers only, so it loads with `torch.load(weights_only=True)`:
format, method (`model.methods`: the method that wrote it; checkpoints from before methods name their field kind in
field_config instead, `model.methods.registry.method_of_checkpoint`), the method's own entries (`Method.checkpoint`;
the field methods: field_config (the field's constructor arguments), field (state dict), occupancy (state dict or
None), space (`radiance.space.Space.to_dict()`: the scene space, its box and bounds)), background ({mode, state}:
`model.background.Background`), optimizer (state dict), step, seconds, lr_factor, rng,
nerfpipe_version (the version that wrote it). Checkpoints written before `space` held `ndc` and `contraction`
(each a dict or None) and took the box and bounds from the scene: `restore_space` reads them so.

Integrity: `save_checkpoint` serialises into memory, writes the bytes atomically (`data.atomic`: a full disk is one
line naming the file, the previous checkpoint stays) and returns their sha256, which `train` records in the run's
manifest.json (`checkpoint_sha256`); `read_checkpoint` refuses a checkpoint whose bytes no longer match it (a
checkpoint without a manifest, an interrupted run's, has nothing to check against). A checkpoint of another format
(another nerfpipe version's layout, an X-ray run's) or of an unknown method is refused naming what was expected.
appearance (`model.appearance.Appearance.to_dict()` or None), camera_opt (`model.camera_opt.CameraOpt.to_dict()`
or None: the pose corrections of `train --refine-poses`).
Checkpoints without background (older runs) load as runs on white; without appearance or camera_opt, as runs
without them.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from nerfpipe.data.atomic import write_bytes
from nerfpipe.data.errors import UserError
from nerfpipe.data.rundir import sha256_file, versions
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.background import Background
from nerfpipe.model.methods.registry import method_names, method_of_checkpoint
from nerfpipe.radiance.contraction import Contraction
from nerfpipe.radiance.ndc import NDC
from nerfpipe.radiance.space import Box, Contracted, NDCSpace, Space, space_from_dict

__all__ = [
    "CHECKPOINT_FORMAT",
    "save_checkpoint",
    "read_checkpoint",
    "restore_background",
    "restore_space",
    "restore_appearance",
    "load_state",
]

CHECKPOINT_FORMAT = 1


def save_checkpoint(
    path: Path,
    *,
    method: str,
    entries: dict[str, Any],
    model: Any,
    opt: torch.optim.Optimizer,
    progress: dict[str, Any],
    extra: dict[str, Any] | None = None,
) -> str:
    """Write a run's checkpoint atomically to `path`: the `method`'s `entries` (`Method.checkpoint`), the model's
    background and appearance codes, the optimiser state, `progress` (step, seconds, lr_factor, rng) and what the
    loop's hooks add (`extra`: camera_opt, the pose corrections); returns the file's sha256 (hex)."""
    appearance = getattr(model, "appearance", None)
    state = {
        "format": CHECKPOINT_FORMAT,
        "method": method,
        **entries,
        "background": {"mode": model.background.mode, "state": model.background.state_dict()},
        "optimizer": opt.state_dict(),
        "step": progress["step"],
        "seconds": progress["seconds"],
        "lr_factor": progress["lr_factor"],
        "rng": progress["rng"],
        "nerfpipe_version": versions().get("nerfpipe", "unknown"),
        "appearance": appearance.to_dict() if appearance is not None else None,
        "camera_opt": None,
        **(extra or {}),
    }
    buf = io.BytesIO()  # torch's own file writer reports a full disk as "unexpected pos"; ours names the errno
    torch.save(state, buf)
    data = buf.getbuffer()
    write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def read_checkpoint(path: Path, device: torch.device | str) -> dict:
    """The train checkpoint's dict on `device`; UserError when missing, unreadable, not ours, or not the file the
    run's manifest.json recorded."""
    expected = _manifest_sha256(path)
    if expected is not None and path.is_file() and (found := sha256_file(path)) != expected:
        raise UserError(
            f"{path}: checkpoint does not match the sha256 recorded in manifest.json (expected "
            f"{expected[:12]}..., found {found[:12]}...): corrupt or replaced"
        )
    state = load_state(
        path,
        device,
        fmt=CHECKPOINT_FORMAT,
        missing="no checkpoint to resume from",
        kind=f"a nerfpipe train checkpoint (format {CHECKPOINT_FORMAT})",
    )
    method = method_of_checkpoint(state)
    if method not in method_names():
        cfg = state.get("field_config")
        kind = cfg.get("kind") if isinstance(cfg, dict) else None
        what = f"method {method!r}" if method is not None else f"no method nerfpipe knows (a field of kind {kind!r})"
        raise UserError(f"{path}: checkpoint written by {what}; expected one of {', '.join(method_names())}")
    return state


def _manifest_sha256(path: Path) -> str | None:
    """The checkpoint hash in the manifest beside `path` (None: no manifest, or one that predates hashes)."""
    try:
        doc = json.loads((path.parent / "manifest.json").read_text())
    except (OSError, ValueError, RecursionError):
        return None
    value = doc.get("checkpoint_sha256") if isinstance(doc, dict) else None
    return value if isinstance(value, str) else None


def load_state(path: Path, device: torch.device | str, *, fmt: object, missing: str, kind: str) -> dict:
    """A checkpoint dict whose "format" is `fmt` (weights_only load); UserError `missing` when there is no file,
    and naming `kind` when it is unreadable or another format. Train and X-ray runs read through this."""
    if not path.is_file():
        raise UserError(f"{path}: {missing}")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # corrupt or foreign file
        raise UserError(f"{path}: cannot read checkpoint ({type(exc).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != fmt:
        found = state.get("format") if isinstance(state, dict) else None
        writer = state.get("nerfpipe_version") if isinstance(state, dict) else None
        by = f" written by nerfpipe {writer}" if writer else ""
        raise UserError(
            f"{path}: not {kind}: found format {found!r}{by}, this is nerfpipe {versions().get('nerfpipe', 'unknown')}"
        )
    return state


def restore_background(state: dict, device: torch.device | str) -> Background:
    """The checkpoint's background model (white, fixed, for checkpoints that predate it)."""
    doc = state.get("background")
    if doc is None:
        return Background("fixed").to(device)
    bg = Background(doc["mode"])
    bg.load_state_dict(doc["state"])
    return bg.to(device)


def restore_appearance(state: dict, device: torch.device | str) -> Appearance | None:
    """The checkpoint's per-image appearance codes (None: trained without, or an older checkpoint)."""
    doc = state.get("appearance")
    return Appearance.from_dict(doc).to(device) if doc is not None else None


def restore_space(state: dict, scene_space: Callable[[type[Space]], Space]) -> Space:
    """The checkpoint's scene space. A checkpoint from before `space` (NDC and contraction stored alone, box and
    bounds taken from the scene) is read as it was trained: `scene_space(kind)` builds what the scene gives."""
    doc = state.get("space")
    if doc is not None:
        try:
            return space_from_dict(doc)
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"checkpoint: unreadable scene space ({exc})") from None
    if state.get("ndc") is not None:
        base = scene_space(NDCSpace)
        return NDCSpace(ndc=NDC.from_dict(state["ndc"]), box=base.box)  # type: ignore[attr-defined]
    if state.get("contraction") is not None:
        return Contracted(contraction=Contraction.from_dict(state["contraction"]), near=scene_space(Contracted).near)
    return scene_space(Box)
