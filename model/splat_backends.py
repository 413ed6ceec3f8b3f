"""The rasteriser the splat stage optimises with, chosen once (`choose_backend`): gsplat's CUDA kernels when the device
is CUDA and `import gsplat` works, else `radiance.splats` (any device; its compositing on CPU runs in the numba kernels
of `radiance.splat_cpu`, elsewhere in torch). Each render returns the image and the projected centres, kept for
their gradient (densification, `model.splat_density`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from nerfpipe.data.errors import UserError
from nerfpipe.radiance import splats as sp
from nerfpipe.radiance.camera import OPENGL_FROM_OPENCV, Intrinsics

__all__ = ["Backend", "choose_backend", "kernel_name"]


@dataclass(frozen=True)
class Backend:
    """A rasteriser, chosen once: its name, why it was chosen, and its render."""

    name: str
    why: str
    render: Callable[[sp.Splats, Tensor, Intrinsics, Tensor], tuple[Tensor, Tensor, Tensor]]
    """(splats, world_from_cam [4, 4], intrinsics, background [3]) -> (rgb [H, W, 3], the projected centres [N, 2]
    in pixels, kept for their gradient (densification), the Gaussians drawn [N] bool)."""


def _torch_render(splats: sp.Splats, world_from_cam: Tensor, intr: Intrinsics, background: Tensor) -> tuple:
    proj = sp.project(splats, world_from_cam, intr)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    return sp.rasterize(proj, intr.w, intr.h, background)["rgb"], proj.means2d, proj.visible


def choose_backend(asked: str, device: torch.device) -> Backend:
    """The backend for `asked` (auto | torch | gsplat) on `device` (module doc); UserError when gsplat cannot run."""
    if asked == "torch":
        return Backend("torch", "asked for", _torch_render)
    try:
        import gsplat  # noqa: F401

        found, missing = True, ""
    except ImportError as exc:
        found, missing = False, str(exc)
    if asked == "gsplat" and not (found and device.type == "cuda"):
        reason = "the device is not CUDA" if found else f"gsplat is not installed ({missing})"
        raise UserError(f"backend: gsplat cannot run here: {reason}; expected backend auto or torch")
    if found and device.type == "cuda":
        return Backend("gsplat", "CUDA device and gsplat installed", _gsplat_render)
    return Backend("torch", "the device is not CUDA" if found else "gsplat is not installed", _torch_render)


def _gsplat_render(splats: sp.Splats, world_from_cam: Tensor, intr: Intrinsics, background: Tensor) -> tuple:
    from gsplat import rasterization

    like = splats.means
    cam_from_world_cv = torch.linalg.inv(torch.as_tensor(world_from_cam).to(like) @ OPENGL_FROM_OPENCV.to(like))
    ks = torch.tensor([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]]).to(like)
    colors, _, meta = rasterization(
        splats.means,
        splats.quats,
        torch.exp(splats.log_scales),
        torch.sigmoid(splats.opacity_logits),
        splats.sh,
        cam_from_world_cv[None],
        ks[None],
        intr.w,
        intr.h,
        sh_degree=sp.sh_degree(splats.sh.shape[1]),
        backgrounds=background.to(like)[None],
        near_plane=0.01,
        eps2d=sp.EPS2D,
        packed=False,
    )
    means2d, radii = meta["means2d"], meta["radii"]  # [1, N, 2]; radii [1, N] or [1, N, 2] by version
    if means2d.requires_grad:
        means2d.retain_grad()
    visible = (radii > 0).reshape(radii.shape[1], -1).all(dim=-1)
    return colors[0], means2d, visible


def kernel_name(backend: Backend, device: torch.device) -> str:
    """What composites the Gaussians: gsplat's CUDA kernels, or `radiance.splats.rasterize`'s numba or torch path."""
    if backend.name == "gsplat":
        return "gsplat CUDA"
    return "numba (radiance.splat_cpu)" if sp.resolve_kernel("auto", device) == "numba" else "torch"
