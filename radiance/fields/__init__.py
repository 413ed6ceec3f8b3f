"""Radiance / attenuation fields behind one interface (`Field`), registered by the kind their `config()` records:
`fast` (TensoRF VM), `vanilla` (the NeRF paper's MLP), `voxel` (a dense trilinear grid, X-ray). `make_field(config)`
rebuilds a field from `Field.config()`."""

from __future__ import annotations

from nerfpipe.radiance.fields.base import Field
from nerfpipe.radiance.fields.fast import TensoRF
from nerfpipe.radiance.fields.vanilla import NeRFMLP, VanillaNeRF
from nerfpipe.radiance.fields.voxel import VoxelField

__all__ = ["FIELDS", "Field", "TensoRF", "NeRFMLP", "VanillaNeRF", "VoxelField", "make_field"]

FIELDS: dict[str, type[Field]] = {"fast": TensoRF, "vanilla": VanillaNeRF, "voxel": VoxelField}
"""Each field class by the kind its `config()` records (checkpoints name it)."""


def make_field(config: dict) -> Field:
    """Build a field from the primitive dict `Field.config()` returned (its "kind" one of `FIELDS`)."""
    kw = dict(config)
    kind = kw.pop("kind", None)
    if kind not in FIELDS:
        raise ValueError(f"unknown field kind {kind!r}: expected one of {', '.join(FIELDS)}")
    return FIELDS[kind](**kw)
