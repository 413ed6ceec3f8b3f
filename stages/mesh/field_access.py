"""Field access for `stages.mesh`: density with empty-space skipping, the box to mesh, vertex colours.

Conventions: the run (`model.run.Run` with the capability density, and colour for vertex colours: `density`,
`density_function`, `color`, `aabb`, `occupancy`, `device`) answers in the scene (training) frame; points go in as
float32 [N, 3] on the run's device, densities come back as float32 [N] on the caller's device. Boxes are [2, 3]
float64 (min, max).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from nerfpipe.model.run import can, require_any
from nerfpipe.stages.mesh.cleanup import vertex_normals
from nerfpipe.stages.mesh.grid import DensityFn

__all__ = [
    "as_np",
    "field_device",
    "has_color",
    "occupancy_binary",
    "density_function",
    "Surface",
    "surface_function",
    "occupied_box",
    "vertex_colors",
]


def as_np(x: Any) -> np.ndarray:
    """A tensor or array-like as a float64 numpy array (on the CPU)."""
    return x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)


def field_device(trained: Any) -> torch.device:
    dev = getattr(trained, "device", None)
    return torch.device(dev) if dev is not None else torch.device("cpu")


def has_color(trained: Any) -> bool:
    """Whether the run gives colours at points (capability colour)."""
    return can(trained, "color")


def occupancy_binary(trained: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """(binary [G, G, G] bool, aabb [2, 3]) of the run's occupancy grid, or None (absent / never updated)."""
    occ = getattr(trained, "occupancy", None)
    if occ is None or getattr(occ, "binary", None) is None:
        return None
    binary = occ.binary.detach().cpu().numpy().astype(bool)
    if binary.all():  # before its first update every cell counts as occupied: no information
        return None
    return binary, as_np(occ.aabb)


def density_function(trained: Any) -> DensityFn:
    """The run's density (its `density_function`: the fastest query for the large batches meshing sends), zero
    without a query in cells the run's occupancy grid marks empty."""
    occ = getattr(trained, "occupancy", None)
    query = trained.density_function()
    device = field_device(trained)

    @torch.inference_mode()
    def plain(x: torch.Tensor) -> torch.Tensor:
        return query(x.to(device, torch.float32)).reshape(-1).float().to(x.device)

    if occupancy_binary(trained) is None:
        return plain

    @torch.inference_mode()
    def skipping(x: torch.Tensor) -> torch.Tensor:
        keep = occ.query(x.to(occ.binary.device)).to(x.device)
        out = torch.zeros(x.shape[0], dtype=torch.float32, device=x.device)
        if bool(keep.any()):
            out[keep] = plain(x[keep])
        return out

    return skipping


@dataclass(frozen=True)
class Surface:
    """What `mesh` thresholds: `values` [N] at scene points (larger inside), and its level where the run fixes it
    (a signed distance's zero; None: the density's level is chosen by `stages.mesh.threshold`)."""

    values: DensityFn
    level: float | None
    what: str
    """density | signed distance (the manifest's `surface`)."""


def surface_function(trained: Any) -> Surface:
    """The run's surface as `mesh` extracts it: the zero level set of a signed distance (capability sdf, negated so
    that inside is larger), else the density's level set (capability density); UserError in one line when the run
    has neither."""
    kind = require_any(trained, ("sdf", "density"), stage="mesh")
    if kind == "density":
        return Surface(values=density_function(trained), level=None, what="density")
    device = field_device(trained)

    @torch.inference_mode()
    def inside(x: torch.Tensor) -> torch.Tensor:
        return -trained.sdf(x.to(device, torch.float32)).reshape(-1).float().to(x.device)

    return Surface(values=inside, level=0.0, what="signed distance")


def occupied_box(trained: Any) -> tuple[np.ndarray, np.ndarray, str]:
    """Scene-frame box to mesh: occupied cells of the occupancy grid (+1 cell), within the aabb; else the aabb."""
    aabb = as_np(trained.aabb).reshape(2, 3)
    box = trained.occupancy.occupied_aabb() if occupancy_binary(trained) is not None else None
    if box is None:
        return aabb[0], aabb[1], "aabb"
    box = as_np(box)
    return np.maximum(box[0], aabb[0]), np.minimum(box[1], aabb[1]), "occupancy grid"


def vertex_colors(trained: Any, verts_scene: np.ndarray, faces_scene: np.ndarray, chunk: int) -> np.ndarray:
    """RGBA uint8 [V, 4]: the field's colour seen along the inward normal."""
    normals = vertex_normals(verts_scene, faces_scene)
    device = field_device(trained)
    out = []
    with torch.inference_mode():
        for a in range(0, len(verts_scene), chunk):
            x = torch.as_tensor(verts_scene[a : a + chunk], dtype=torch.float32, device=device)
            d = -torch.as_tensor(normals[a : a + chunk], dtype=torch.float32, device=device)
            d = torch.where(d.norm(dim=1, keepdim=True) > 0, d, torch.tensor([0.0, 0.0, -1.0], device=device))
            out.append(trained.color(x, d).float().clamp(0, 1).cpu().numpy())  # chunks as the run likes
    rgb = np.concatenate(out) if out else np.zeros((0, 3), np.float32)
    rgba = np.concatenate([np.rint(rgb * 255), np.full((len(rgb), 1), 255.0)], axis=1)
    return rgba.astype(np.uint8)
