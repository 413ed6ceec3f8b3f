"""Voxel network weights files: the network's configuration and parameters, and how they were made.

A weights file is a torch file (read weights-only) holding {"format": WEIGHTS_FORMAT, "voxel_net_config": dict,
"voxel_net": state dict (floating tensors as float16: half the size, no measurable change of the predictions,
docs/VOXELS.md), "provenance": dict}. `make pretrain-voxels` writes one and the repository ships
`weights/pretrained.pt` with `weights/pretrained.json` beside it (the command, the commit, the data, the figures).
Nothing is downloaded.
"""

from __future__ import annotations

import io
from pathlib import Path

import torch

from nerfpipe.data.atomic import write_bytes
from nerfpipe.data.errors import UserError
from nerfpipe.model.voxels.net import VoxelNet

__all__ = ["WEIGHTS_FORMAT", "PRETRAINED", "read_weights", "write_weights", "load_net"]

WEIGHTS_FORMAT = "nerfpipe-voxel-weights-1"
PRETRAINED = Path(__file__).parent / "weights" / "pretrained.pt"
"""The network shipped with nerfpipe (`weights="pretrained"`)."""


def read_weights(which: str | Path) -> tuple[dict, dict, dict]:
    """'pretrained' or a weights file -> (net config, state dict, provenance); UserError in one line when it is
    missing or not voxel weights."""
    path = PRETRAINED if str(which) == "pretrained" else Path(which)
    if not path.is_file():
        what = (
            "the shipped voxel weights (make pretrain-voxels writes them)" if str(which) == "pretrained" else "a file"
        )
        raise UserError(f"weights: {path} not found ({what})")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt or foreign
        raise UserError(f"weights: {path}: not voxel weights (unreadable: {type(exc).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != WEIGHTS_FORMAT:
        raise UserError(f"weights: {path}: not voxel weights (expected format {WEIGHTS_FORMAT})")
    return dict(state["voxel_net_config"]), state["voxel_net"], dict(state.get("provenance") or {})


def write_weights(path: Path, config: dict, state: dict, provenance: dict) -> Path:
    """Write a weights file atomically (floating tensors float16 on the CPU, integer buffers as they are)."""
    buf = io.BytesIO()
    cpu = {
        k: (v.detach().to("cpu", torch.float16) if v.is_floating_point() else v.detach().cpu())
        for k, v in state.items()
    }
    torch.save({"format": WEIGHTS_FORMAT, "voxel_net_config": config, "voxel_net": cpu, "provenance": provenance}, buf)
    return write_bytes(path, buf.getvalue())


def load_net(which: str | Path, device: torch.device) -> tuple[VoxelNet, dict]:
    """The network of a weights file, float32, in eval mode on `device`, and its provenance."""
    config, state, provenance = read_weights(which)
    net = VoxelNet(**config)
    net.load_state_dict({k: (v.float() if v.is_floating_point() else v) for k, v in state.items()})
    return net.to(device).eval(), provenance
