"""GNT weights files: the network's configuration and parameters, and how they were made.

A weights file is a torch file (read weights-only) holding {"format": WEIGHTS_FORMAT, "gnt_net_config": dict,
"gnt_net": state dict, "provenance": dict}; `make pretrain-gnt` writes one (`model.methods.gnt.pretrain`) and the
repository ships `weights/pretrained.pt` with its provenance beside it (`weights/pretrained.json`: the command, the
commit, the data recipe, the figures). A gnt run's checkpoint.pt holds the same two entries, so `--init` takes
either. Nothing is downloaded.
"""

from __future__ import annotations

import io
from pathlib import Path

import torch

from nerfpipe.data.atomic import write_bytes
from nerfpipe.data.errors import UserError
from nerfpipe.model.methods.gnt.net import GntNet, stored_config

__all__ = ["WEIGHTS_FORMAT", "PRETRAINED", "read_weights", "write_weights", "build_net"]

WEIGHTS_FORMAT = "nerfpipe-gnt-weights-1"
PRETRAINED = Path(__file__).parent / "weights" / "pretrained.pt"
"""The model shipped with nerfpipe (`--init pretrained`)."""


def read_weights(init: str, device: torch.device) -> tuple[dict, dict, dict]:
    """`init` ('pretrained', a weights file or a gnt checkpoint.pt) -> (net config, completed by `stored_config`,
    state dict, provenance); UserError in one line when it is missing or not gnt weights."""
    path = PRETRAINED if init == "pretrained" else Path(init)
    if not path.is_file():
        what = "the shipped pretrained gnt weights (make pretrain-gnt writes them)" if init == "pretrained" else init
        raise UserError(f"init: {path} not found ({what})")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # corrupt or foreign
        raise UserError(f"init: {path}: not gnt weights (unreadable: {type(exc).__name__})") from None
    if not isinstance(state, dict) or "gnt_net" not in state or "gnt_net_config" not in state:
        raise UserError(f"init: {path}: not gnt weights (expected a weights file or a gnt run's checkpoint.pt)")
    return stored_config(state["gnt_net_config"]), state["gnt_net"], dict(state.get("provenance") or {})


def build_net(config: dict, state: dict | None, device: torch.device) -> GntNet:
    """The network a (stored) configuration names, with `state` loaded when given; UserError in one line when the
    state does not fit it."""
    net = GntNet.from_config(config).to(device)
    if state is not None:
        try:
            net.load_state_dict(state)
        except RuntimeError as exc:
            raise UserError(f"gnt weights do not fit the network they name ({str(exc).splitlines()[0]})") from None
    return net


def write_weights(path: Path, config: dict, state: dict, provenance: dict) -> Path:
    """Write a weights file atomically (float32 tensors on the CPU)."""
    buf = io.BytesIO()
    cpu = {k: v.detach().to("cpu", torch.float32) for k, v in state.items()}
    torch.save({"format": WEIGHTS_FORMAT, "gnt_net_config": config, "gnt_net": cpu, "provenance": provenance}, buf)
    return write_bytes(path, buf.getvalue())
