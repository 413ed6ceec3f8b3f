"""One device resolver for every stage: "auto" | "cpu" | "cuda" | "cuda:N" -> torch.device, or a UserError."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import torch
from torch import Tensor

from nerfpipe.data.errors import UserError

__all__ = ["resolve_device", "cpu_threads", "rays_per_chunk", "render_in_chunks", "CUDA_CHUNK_FACTOR"]


def resolve_device(name: str | torch.device) -> torch.device:
    """ "auto": CUDA when torch sees a GPU, else the CPU. A CUDA device without CUDA is a UserError."""
    if isinstance(name, torch.device):
        return name
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise UserError(f"device: unknown device {name!r} (expected auto, cpu, cuda, cuda:N)") from None
    if dev.type not in ("cpu", "cuda"):
        raise UserError(f"device: unknown device {name!r} (expected auto, cpu, cuda, cuda:N)")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"device: {name} requested but torch sees no CUDA device")
    return dev


CUDA_CHUNK_FACTOR = 32
"""On CUDA an inference chunk holds this many times a model's CPU chunk (8192 -> 262,144 rays for the grid fields):
the early-stopping march runs one round of small kernels and host syncs per slab of every chunk, so 8192-ray chunks
left an H200 launch-bound (lego_800: 0.36 M rays/s in eval, 0.8 frames/s in the viewer at 800x800; docs/GPU.md)."""


def rays_per_chunk(cpu_chunk: int, device: torch.device) -> int:
    """Rays per inference chunk on `device`, from a model's CPU chunk (sized to CPU caches and memory)."""
    return cpu_chunk * CUDA_CHUNK_FACTOR if device.type == "cuda" else cpu_chunk


@contextlib.contextmanager
def cpu_threads(n: int | None) -> Iterator[None]:
    """torch's intra-op CPU threads set to n inside the block (None: unchanged), restored afterwards."""
    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def render_in_chunks(
    render: Callable[[Tensor, Tensor], dict[str, Tensor]],
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    chunk: int,
    device: torch.device,
    *,
    median: bool = True,
) -> dict[str, Tensor]:
    """A run's `render_rays` in chunks of `chunk` rays moved to `device` as float32: `render(o, d)` -> dict with at
    least rgb, depth, acc (and depth_median when `median`) -> those keys [R, ...] concatenated."""
    if rays_o.shape != rays_d.shape or rays_o.ndim != 2 or rays_o.shape[-1] != 3:
        raise ValueError(f"expected rays_o, rays_d [R, 3], got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}")
    keys = ("rgb", "depth", "depth_median", "acc") if median else ("rgb", "depth", "acc")
    parts: dict[str, list[Tensor]] = {k: [] for k in keys}
    for i in range(0, rays_o.shape[0], chunk):
        out = render(rays_o[i : i + chunk].to(device, torch.float32), rays_d[i : i + chunk].to(device, torch.float32))
        for k in parts:
            parts[k].append(out[k])
    empty = {"rgb": (0, 3)}  # no rays: each key empty in its own shape (rgb [0, 3], the others [0])
    return {k: torch.cat(v) if v else torch.zeros(empty.get(k, (0,)), device=device) for k, v in parts.items()}
