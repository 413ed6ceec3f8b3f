"""GNT's `TrainModel`: rays -> samples -> the K nearest source photos' features at each sample -> the network
(`model.methods.gnt.net`) -> colour, coverage and depth.

Samples: S a ray, stratified (jittered while training, at interval middles otherwise) over the ray's range
(`RayRange`): uniform in depth through the object's box for a box scene, uniform in inverse depth from the near plane
to the far one (or to infinity) otherwise, as IBRNet and GNT sample LLFF scenes.
Sources: the training photos (`model.methods.gnt.sources`); each ray reads the `k` whose view of its range's middle
is closest in angle to the ray, never its own photo while training. While training, features are computed with
gradients for the photos a batch reads (the loop draws a step's rays from a few photos: `hooks.GntBatches`); at
inference for every photo once, kept until the weights change.
Output: rgb = alpha c + (1 - alpha) background, acc = alpha (0 for a ray that misses the box: its range is
empty), depth = sum_s w_s t_s, depth_median where the read-out weights reach 0.5 (weights: the read-out's softmax
over the ray).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from nerfpipe.data.transforms import Scene
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.background import Background
from nerfpipe.model.field_model import param_groups
from nerfpipe.model.methods.gnt.net import GntNet
from nerfpipe.model.methods.gnt.sources import Sources, gather_texels, texels
from nerfpipe.radiance.aabb import ray_aabb_segment

__all__ = ["RayRange", "ray_range", "GntModel", "NEAR_FRACTION"]

NEAR_FRACTION = 0.05
"""Without a near plane in transforms.json, rays start at this fraction of the cameras' median distance to the
scene's centre."""


@dataclass(frozen=True)
class RayRange:
    """Where a ray's samples lie: through `aabb` (box scenes: uniform in depth) or, without one, from near to far
    (inf allowed) uniform in inverse depth."""

    near: float
    far: float
    aabb: tuple[tuple[float, ...], tuple[float, ...]] | None = None

    def segment(self, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        """Each ray's [t_near, t_far] [R] (a ray that misses the box: an empty segment at its entry)."""
        if self.aabb is None:
            return torch.full_like(o[:, 0], self.near), torch.full_like(o[:, 0], self.far)
        t0, t1 = ray_aabb_segment(o, d, torch.tensor(self.aabb, dtype=o.dtype, device=o.device), self.near, self.far)
        return t0, torch.maximum(t0, t1)

    def samples(self, o: Tensor, d: Tensor, n: int, jitter: Tensor | None) -> tuple[Tensor, Tensor]:
        """t [R, n] along each ray and its position in the range t01 [R, n] in [0, 1]; jitter [R, n] in [0, 1) or
        None (interval middles)."""
        r = o.shape[0]
        s = (torch.arange(n, dtype=o.dtype, device=o.device) + 0.5) / n  # [n]
        s = s.expand(r, n) if jitter is None else (torch.arange(n, dtype=o.dtype, device=o.device) + jitter) / n
        t0, t1 = self.segment(o, d)
        if self.aabb is not None:
            return t0[:, None] + s * (t1 - t0)[:, None], s
        inv = (1 - s) / t0[:, None] + s / t1[:, None]  # inverse depth, 1 / inf = 0
        return 1.0 / inv, s

    def middle(self, o: Tensor, d: Tensor) -> Tensor:
        """The point [R, 3] the sources are chosen for: the middle of the box segment, or twice the near plane."""
        t0, t1 = self.segment(o, d)
        t = 0.5 * (t0 + t1) if self.aabb is not None else 2.0 * t0
        return o + d * t[:, None]

    def to_dict(self) -> dict:
        return {"near": self.near, "far": self.far if math.isfinite(self.far) else "inf", "aabb": self.aabb}

    @staticmethod
    def from_dict(doc: dict) -> RayRange:
        aabb = doc.get("aabb")
        far = math.inf if doc["far"] == "inf" else float(doc["far"])
        return RayRange(float(doc["near"]), far, None if aabb is None else tuple(tuple(map(float, a)) for a in aabb))


def ray_range(scene: Scene, box: bool) -> tuple[RayRange, str]:
    """Where a scene's rays are sampled, and why: through its aabb (objects in their box), else from the near plane
    (transforms.json's, or `NEAR_FRACTION` of the cameras' distance) to the far one, in inverse depth."""
    aabb = tuple(tuple(float(v) for v in row) for row in scene.aabb)
    if box:
        return RayRange(scene.near, scene.far, aabb), "through the scene's aabb, uniform in depth"
    near, why = scene.near, "transforms.json's near plane"
    if not near > 0:
        centre = (torch.tensor(scene.aabb[0]) + torch.tensor(scene.aabb[1])) / 2
        dist = torch.stack([torch.as_tensor(f.world_from_cam[:3, 3]) for f in scene.frames]).float() - centre.float()
        near = NEAR_FRACTION * float(torch.linalg.vector_norm(dist, dim=-1).median())
        why = f"{NEAR_FRACTION} x the cameras' median distance to the scene's centre"
    far = scene.far if scene.far > near else math.inf
    return RayRange(near, far, None), f"from {near:.3g} ({why}) to {far:.3g}, uniform in inverse depth"


@dataclass(eq=False)
class GntModel:
    """GNT over one scene's source photos (module doc): a `model.methods.base.TrainModel`."""

    net: GntNet
    sources: Sources
    range: RayRange
    samples: int
    k: int
    background: Background | None = None
    appearance: Appearance | None = None
    chunk: int = 256
    """Rays a render chunk on CPU (x 32 on CUDA, `model.device.rays_per_chunk`): 8,192 rays x 64 samples x 8 views
    x 32 channels is 0.5 GB a tensor of the view transformer."""
    random_draws_per_ray: int = 0
    """One jitter a sample (set to `samples`: data-parallel runs place a rank's draws by it)."""
    space: Any = None
    _maps: tuple[Tensor, tuple[int, int]] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.random_draws_per_ray = self.samples

    def render(
        self, o: Tensor, d: Tensor, background: Tensor, *, train: bool, view: Tensor | None = None, **_: Any
    ) -> dict[str, Tensor]:
        """Rays o, d [R, 3] (unit d), background [R, 3] or [3] -> dict(rgb [R, 3], acc [R], depth [R],
        depth_median [R], samples). `view` [R]: each ray's training photo (excluded from its sources while
        training)."""
        r, n = o.shape[0], self.samples
        jitter = torch.rand(r, n, dtype=o.dtype, device=o.device) if train else None
        t, t01 = self.range.samples(o, d, n, jitter)  # [R, S]
        x = o[:, None, :] + d[:, None, :] * t[..., None]  # [R, S, 3]
        exclude = view.long() if (train and view is not None) else None
        k = min(self.k, self.sources.n - 1) if exclude is not None else self.k  # a ray's own photo left out
        chosen = self.sources.select(self.range.middle(o, d), d, k, exclude)  # [R, K]
        uv, seen = self.sources.project(x, chosen)  # [R, S, K, 2], [R, S, K]
        (maps, (hf, wf)), local = self._feature_maps(chosen, train)  # texels [U hf wf, C]
        k = chosen.shape[1]  # at most the sources there are
        flat_uv = uv.reshape(-1, 2)
        h, w = self.sources.size
        map_uv = flat_uv * torch.tensor([wf / w, hf / h], dtype=uv.dtype, device=uv.device)
        view_of = local[:, None, :].expand(r, n, k).reshape(-1)
        feats = gather_texels(maps, (hf, wf), view_of, map_uv)  # [R S K, C]
        src_of = chosen[:, None, :].expand(r, n, k).reshape(-1)
        pixels = gather_texels(self.sources.pixels, (h, w), src_of, flat_uv)  # [R S K, 4]
        views = torch.cat([feats, pixels], dim=-1).reshape(r, n, k, -1)
        src_dirs = self.sources.directions(x, chosen)  # [R, S, K, 3]
        diff = d[:, None, None, :] - src_dirs
        ray_diff = torch.cat([diff, (d[:, None, None, :] * src_dirs).sum(-1, keepdim=True)], dim=-1)
        out = self.net(views, ray_diff, seen, t01)
        w_ = out["weights"]
        alpha = out["alpha"] * (t[:, -1] > t[:, 0])  # a ray that misses the box covers nothing
        rgb = alpha[:, None] * out["rgb"] + (1 - alpha[:, None]) * background
        depth = (w_ * t).sum(1)
        cum = w_.detach().cumsum(1)
        median_idx = (cum < 0.5).sum(1).clamp(max=n - 1)
        result = {
            "rgb": rgb,
            "acc": alpha,
            "depth": depth,
            "depth_median": t.gather(1, median_idx[:, None])[:, 0],
            "samples": torch.tensor(float(r * n)),
        }
        if self.appearance is not None:
            result["rgb"] = self.appearance(result["rgb"], result["acc"], background, view)
        return result

    def _feature_maps(self, chosen: Tensor, train: bool) -> tuple[tuple[Tensor, tuple[int, int]], Tensor]:
        """The feature maps as texels [U h w, C] with their size (h, w), and each chosen source's map, local [R, K]:
        while training only the sources chosen (with gradients), otherwise every source's, computed once."""
        if train or torch.is_grad_enabled():
            used, local = chosen.unique(return_inverse=True)
            maps = self.net.features(self.sources.images[used])
            return (texels(maps), tuple(maps.shape[-2:])), local
        if self._maps is None:
            with torch.no_grad():
                maps = torch.cat(
                    [self.net.features(self.sources.images[i : i + 16]) for i in range(0, self.sources.n, 16)]
                )
                self._maps = (texels(maps), tuple(maps.shape[-2:]))
        return self._maps, chosen

    def forget_features(self) -> None:
        """The weights changed: the cached feature maps are stale."""
        self._maps = None

    # ------------------------------------------------------------------------------------------------ TrainModel
    def param_groups(self, lr: float) -> list[dict]:
        return param_groups([{"params": list(self.net.parameters()), "lr": lr}], self.background, self.appearance, lr)

    def train_mode(self, on: bool) -> None:
        self.net.train(on)
        self.forget_features()

    def after_step(self) -> None:
        self.forget_features()

    def learned(self) -> dict[str, torch.nn.Module]:
        mods = {"net": self.net, "background": self.background, "appearance": self.appearance}
        return {k: v for k, v in mods.items() if v is not None}

    def snapshot(self) -> dict[str, Any]:
        return {k: copy.deepcopy(v.state_dict()) for k, v in self.learned().items()}

    def restore(self, snapshot: dict[str, Any]) -> bool:
        for key, mod in self.learned().items():
            mod.load_state_dict(snapshot[key])
        self.forget_features()
        return False

    def describe(self) -> dict[str, Any]:
        """The manifest's record: the network's configuration, sources, samples and the rays' range."""
        return {
            "net": self.net.config(),
            "parameters": sum(p.numel() for p in self.net.parameters()),
            "gnt": {
                "source_views": self.k,
                "sources": self.sources.n,
                "source_size": list(self.sources.size),
                "samples_per_ray": self.samples,
                "range": self.range.to_dict(),
            },
        }
