"""Radiance / attenuation fields behind one interface (`Field`): `fast` (TensoRF VM, default) and
`vanilla` (the NeRF paper's MLP). `make_field(config)` rebuilds a field from `Field.config()`."""

from __future__ import annotations

from nerfpipe.radiance.fields.base import Field
from nerfpipe.radiance.fields.fast import TensoRF
from nerfpipe.radiance.fields.vanilla import NeRFMLP, VanillaNeRF

__all__ = ["Field", "TensoRF", "NeRFMLP", "VanillaNeRF", "make_field"]


def make_field(config: dict) -> Field:
    """Build a field from the primitive dict `Field.config()` returned ("kind": "fast" | "vanilla")."""
    kw = dict(config)
    kind = kw.pop("kind", None)
    if kind == "fast":
        return TensoRF(**kw)
    if kind == "vanilla":
        return VanillaNeRF(**kw)
    raise ValueError(f"unknown field kind {kind!r}: expected 'fast' or 'vanilla'")
