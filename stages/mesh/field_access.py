"""Field access for `stages.mesh`: density with empty-space skipping, the box to mesh, vertex colours.

Conventions: the field (anything with the `model.Trained` attributes `density`, `color`, `aabb`, `occupancy`,
`device`, `ndc`, `field`) lives in the scene (training) frame; points go in as float32 [N, 3] on the field's
device, densities come back as float32 [N] on the caller's device. Boxes are [2, 3] float64 (min, max).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from nerfpipe.stages.mesh.cleanup import vertex_normals
from nerfpipe.stages.mesh.grid import DensityFn

__all__ = [
    "as_np",
    "field_device",
    "has_color",
    "occupancy_binary",
    "density_function",
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
    f = getattr(trained, "field", None)
    return bool(getattr(f if f is not None else trained, "has_color", True))


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
    """The field's density, zero without a query in cells the run's occupancy grid marks empty.

    Calls the run's `Field.density` directly when there is one and the field lives in the scene frame:
    `Trained.density` splits queries into small render-sized chunks, several times slower on a CPU than the
    large chunks meshing sends. Runs whose field lives in another space (NDC, contracted) go through
    `Trained.density`, which maps scene points into it (`radiance.space`).
    """
    occ = getattr(trained, "occupancy", None)
    field = getattr(trained, "field", None)
    direct = isinstance(field, torch.nn.Module) and hasattr(field, "density") and trained.space.scene_frame
    query = field.density if direct else trained.density
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
