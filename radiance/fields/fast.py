"""TensoRF-style VM field (Chen et al. 2022): the default, fast field. Pure torch.

The scene box `aabb` [2, 3] is mapped to [-1, 1]^3. Density and appearance are each a sum of
vector-matrix (VM) components: for each axis m, a plane over the two other axes times a line along m,
    f(x) = sum_m sum_r P_m,r(x_u, x_v) * L_m,r(x_m)   (bilinear / linear interpolation, align_corners).
Each plane and its line hold their own tensor ([1, C_m, R, R] and [1, C_m, R, 1]) and component count C_m
(`density_rank` / `app_rank`: one count for all three, or one per plane xy, xz, yz: TensoRF's LLFF setting puts most
in the xy plane, a forward-facing capture's image plane).
- density: `density_rank` components per axis, summed, then
  sigma = density_scale * act(f + density_shift)   (per world unit; never overflows: f is clamped at 1e4),
  act = softplus (`density_activation`, the default, TensoRF's for objects, with shift -10) or relu (TensoRF's LLFF
  setting, shift 0: exactly zero where f < 0; `stages.train.rules.NDCRules` measures it on forward-facing scenes),
- colour: `app_rank` components per axis give sum(app_rank) features, a linear basis maps them to
  `app_dim`, and a small MLP (with optional view-direction encoding) gives RGB through a sigmoid.
`upsample(resolution)` resamples planes and lines to a finer grid (coarse-to-fine as TensoRF does);
the optimizer must then be rebuilt. `has_color=False` gives a density-only field (X-ray).

Positions outside the box get zero density (the renderer only samples inside it anyway).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfpipe.radiance.fields.base import Field, check_points
from nerfpipe.radiance.fields.encodings import positional_encoding
from nerfpipe.radiance.fields.vm_tables import VmTables

__all__ = [
    "TensoRF",
    "TENSORF_RANK",
    "DENSITY_ACTIVATIONS",
    "DEFAULT_ACTIVATION",
    "DEFAULT_HIDDEN",
    "split_rank",
    "vm_node_volume",
    "factors_key",
]

DENSITY_SHIFT = {"softplus": -10.0, "relu": 0.0}
"""Each density activation's shift (TensoRF's: softplus(f - 10) starts near zero density, relu(f) is zero below 0)."""
DENSITY_ACTIVATIONS = tuple(DENSITY_SHIFT)
DEFAULT_ACTIVATION = "softplus"
"""TensoRF's default activation, and the one of every field saved before the option existed."""
DEFAULT_HIDDEN = 64
"""Width of the colour MLP's two hidden layers by default (`TensoRF(hidden=...)`), and that of every run recorded
before train's `--mlp-width` existed."""

TENSORF_RANK = (16, 48)
"""TensoRF's density and appearance components per plane: the field's default (and every run's before `--rank`)."""

# Plane m spans axes PLANE_AXES[m]; its line runs along LINE_AXIS[m].
PLANE_AXES = ((0, 1), (0, 2), (1, 2))
LINE_AXIS = (2, 1, 0)


# grid_sample's CPU backward parallelises over the batch only: one plane on 2 threads leaves one idle. Splitting its
# channels into CHANNEL_SPLIT groups (a batch of 4) balances it; each channel is interpolated exactly as before
# (docs/MEASUREMENTS.md, "Fields").
CHANNEL_SPLIT = 4


def _vm_inputs(xn: Tensor) -> tuple[Tensor, Tensor]:
    # Slices, not index lists: PLANE_AXES = (0, 1), (0, 2), (1, 2) and LINE_AXIS = (2, 1, 0).
    plane_uv = torch.stack([xn[:, :2], xn[:, ::2], xn[:, 1:]])  # [3, N, 2] (x -> W, y -> H)
    line_w = xn.flip(1).T  # [3, N]
    return plane_uv, torch.stack([torch.zeros_like(line_w), line_w], dim=-1)  # [3, N, 2]


def _sample_one(grid: Tensor, uv: Tensor) -> Tensor:
    """grid [1, C, H, W], uv [N, 2] -> bilinear (align_corners) samples [C, N], channels split in groups."""
    c = grid.shape[1]
    k = CHANNEL_SPLIT if c % CHANNEL_SPLIT == 0 else 1
    g = grid.reshape(k, c // k, *grid.shape[2:])
    out = F.grid_sample(g, uv[None, :, None, :].expand(k, -1, -1, -1), mode="bilinear", align_corners=True)
    return out.reshape(c, -1)


def _plane_features(planes: Sequence[Tensor], lines: Sequence[Tensor], xn: Tensor) -> list[Tensor]:
    """planes (xy, xz, yz) [1, C_m, H_m, W_m], lines (z, y, x) [1, C_m, L_m, 1], xn [N, 3] in [-1, 1] -> each axis's
    products [C_m, N] (a plane and its line may have their own component count and sizes)."""
    plane_uv, line_uv = _vm_inputs(xn)
    pairs = enumerate(zip(planes, lines, strict=True))
    return [_sample_one(p, plane_uv[m]) * _sample_one(ln, line_uv[m]) for m, (p, ln) in pairs]


def vm_node_volume(planes: Sequence[Tensor], lines: Sequence[Tensor]) -> Tensor:
    """planes (xy, xz, yz) [1, C, R, R], lines (z, y, x) [1, C, R, 1] -> the sum of each plane times its line at every
    grid node, [1, 1, R, R, R] indexed (z, y, x) as `F.grid_sample` reads a volume (no gradient). A plane's bilinear
    interpolation times its line's linear one is the trilinear interpolation of their products at the nodes, so
    trilinear sampling of this volume gives `_plane_features`' summed products exactly (up to float rounding) from 8
    values a point instead of 3 x (4 + 2) x C."""
    with torch.no_grad():
        p = [t.detach()[0] for t in planes]  # [C, R, R] each
        ln = [t.detach()[0, :, :, 0] for t in lines]  # [C, R] each
        vol = torch.einsum("cyx,cz->zyx", p[0], ln[0])  # plane (x, y), line z
        vol += torch.einsum("czx,cy->zyx", p[1], ln[1])  # plane (x, z), line y
        vol += torch.einsum("czy,cx->zyx", p[2], ln[2])  # plane (y, z), line x
    return vol[None, None].contiguous()


def factors_key(factors: Sequence[Tensor]) -> tuple:
    """What a cache built from `factors` depends on as far as torch can tell: their storage, version counters, shapes,
    dtypes and devices (an in-place change behind the version counter, a fused optimiser step, is not seen)."""
    return tuple((t.data_ptr(), t._version, t.shape, t.dtype, t.device) for t in factors)


def _plane_features_reference(planes: Sequence[Tensor], lines: Sequence[Tensor], xn: Tensor) -> list[Tensor]:
    """Plain twin of `_plane_features` (index lists, one grid_sample per grid, channels unsplit; for tests)."""
    out = []
    for m, (p, ln) in enumerate(zip(planes, lines, strict=True)):
        uv = xn[:, list(PLANE_AXES[m])]  # [N, 2] (first axis -> W, second -> H)
        w = xn[:, LINE_AXIS[m]]
        line_uv = torch.stack([torch.zeros_like(w), w], dim=-1)  # [N, 2]
        ps = F.grid_sample(p, uv[None, :, None, :], mode="bilinear", align_corners=True)  # [1, C, N, 1]
        ls = F.grid_sample(ln, line_uv[None, :, None, :], mode="bilinear", align_corners=True)  # [1, C, N, 1]
        out.append((ps * ls)[0, :, :, 0])
    return out


def _plane_tv(planes: Tensor) -> Tensor:
    """planes [P, C, H, W] -> sum over the P planes of 2 * (mean squared H-difference + mean squared W-difference)
    (the field passes each plane alone, P = 1)."""
    dh = (planes[:, :, 1:, :] - planes[:, :, :-1, :]).pow(2).mean(dim=(1, 2, 3))
    dw = (planes[:, :, :, 1:] - planes[:, :, :, :-1]).pow(2).mean(dim=(1, 2, 3))
    return 2.0 * (dh + dw).sum()


def tv_pairs(shape: torch.Size, texels: int, gen: torch.Generator | None, device: torch.device) -> Tensor:
    """K = texels random neighbour pairs per plane of planes [P, C, H, W] (the same in every channel), half along H
    and half along W -> flat indices into H * W, [2 (texel, its neighbour), P, 1, K]."""
    n, _, h, w = shape
    if texels < 2 or h < 2 or w < 2:
        raise ValueError(f"expected texels >= 2 and planes at least 2 x 2, got {texels} and {tuple(shape)}")
    k = texels // 2
    dev = gen.device if gen is not None else device
    i = torch.randint(h - 1, (n, 1, k), generator=gen, device=dev)  # along H: rows with a next row
    j = torch.randint(w, (n, 1, k), generator=gen, device=dev)
    along_h = torch.stack([i * w + j, (i + 1) * w + j])
    i = torch.randint(h, (n, 1, k), generator=gen, device=dev)  # along W: columns with a next column
    j = torch.randint(w - 1, (n, 1, k), generator=gen, device=dev)
    along_w = torch.stack([i * w + j, i * w + j + 1])
    return torch.cat([along_h, along_w], dim=-1).to(device)


def _pair_differences(planes: Tensor, pairs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """planes [P, C, H, W], pairs from `tv_pairs` -> (neighbour minus texel [P, C, K], the texels' and the
    neighbours' flat indices expanded over the channels [P, C, K])."""
    n, c = planes.shape[:2]
    k = pairs.shape[-1]
    a, b = pairs[0].expand(n, c, k), pairs[1].expand(n, c, k)
    flat = planes.reshape(n, c, -1)
    return flat.gather(2, b) - flat.gather(2, a), a, b


def plane_tv_sampled(planes: Tensor, pairs: Tensor) -> Tensor:
    """Unbiased estimate of `_plane_tv` from `tv_pairs` (differentiable; the plain twin of `add_plane_tv_grad_`).
    Each pair is half of the estimate: 2 * (mean over H-pairs + mean over W-pairs) = 4 * mean over all pairs."""
    diff, _, _ = _pair_differences(planes, pairs)
    return 4.0 * diff.pow(2).mean(dim=(1, 2)).sum()


@torch.no_grad()
def add_plane_tv_grad_(planes: nn.Parameter, pairs: Tensor, weight: float) -> float:
    """planes.grad += weight * d(plane_tv_sampled)/d(planes), touching only the sampled texels (the dense gradient
    of a gather costs as much as the whole plane); returns the estimate's value."""
    diff, a, b = _pair_differences(planes, pairs)
    if planes.grad is None:
        planes.grad = torch.zeros_like(planes)
    n, c, k = diff.shape
    g = planes.grad.view(n, c, -1)
    step = diff * (weight * 8.0 / (c * k))  # d/d(diff) of 4 * mean(diff^2) over C * K entries, per plane
    g.scatter_add_(2, b, step)
    g.scatter_add_(2, a, -step)
    return float(4.0 * diff.pow(2).mean(dim=(1, 2)).sum())


Rank = int | Sequence[int]
"""Components per plane: one count for all three, or one per plane (xy, xz, yz)."""


def per_plane(rank: Rank, what: str) -> tuple[int, int, int]:
    """`rank` as three counts (xy, xz, yz); ValueError unless each is >= 1."""
    ranks = (int(rank),) * 3 if isinstance(rank, int) else tuple(int(r) for r in rank)
    if len(ranks) != 3 or min(ranks) < 1:
        raise ValueError(f"expected {what} as one count or three (xy, xz, yz plane), each >= 1, got {rank!r}")
    return ranks  # type: ignore[return-value]


def split_rank(rank: Sequence[int]) -> tuple[Rank, Rank]:
    """train's `--rank`: two counts (density, appearance: every plane alike) or six (density's xy, xz, yz planes, then
    appearance's) -> (density_rank, app_rank) as `TensoRF` takes them; ValueError otherwise."""
    values = tuple(int(r) for r in rank)
    if len(values) not in (2, 6) or min(values) < 1:
        raise ValueError(
            f"expected rank as 2 counts (density, appearance) or 6 (density xy, xz, yz, appearance xy, xz, yz), "
            f"each >= 1, got {tuple(rank)}"
        )
    if len(values) == 2:
        return values[0], values[1]
    return values[:3], values[3:]


def _mean_abs(factors: Sequence[Tensor]) -> Tensor:
    """Mean absolute value over every texel of `factors` (tensors of any sizes)."""
    return sum(t.abs().sum() for t in factors) / sum(t.numel() for t in factors)


def _uniform(ranks: tuple[int, int, int]) -> int | list[int]:
    return ranks[0] if len(set(ranks)) == 1 else list(ranks)


class TensoRF(Field):
    """VM-decomposed density (+ appearance) grid with a small shading MLP.

    `density_rank` / `app_rank` give the components of each plane (xy, xz, yz) and its line (z, y, x): one count, or
    three (TensoRF's LLFF setting puts most in the xy plane, a forward-facing capture's image plane)."""

    def __init__(
        self,
        *,
        aabb: Tensor | list,
        resolution: int = 128,
        density_rank: Rank = TENSORF_RANK[0],
        app_rank: Rank = TENSORF_RANK[1],
        app_dim: int = 27,
        hidden: int = DEFAULT_HIDDEN,
        view_freqs: int = 2,
        feat_freqs: int = 0,
        has_color: bool = True,
        view_dependent: bool = True,
        density_shift: float | None = None,
        density_scale: float = 25.0,
        density_activation: str = DEFAULT_ACTIVATION,
        init_std: float = 0.1,
    ) -> None:
        super().__init__()
        aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3)
        if not bool((aabb[1] > aabb[0]).all()):
            raise ValueError(f"expected aabb [[min], [max]] with max > min, got {aabb.tolist()}")
        self.register_buffer("aabb", aabb)
        self.resolution = int(resolution)
        self.density_rank = per_plane(density_rank, "density_rank")
        self.app_rank = per_plane(app_rank, "app_rank")
        self.app_dim, self.hidden = app_dim, hidden
        self.view_freqs, self.feat_freqs = view_freqs, feat_freqs
        self.has_color = has_color
        self.view_dependent = view_dependent and has_color
        if density_activation not in DENSITY_ACTIVATIONS:
            raise ValueError(f"expected density_activation in {DENSITY_ACTIVATIONS}, got {density_activation!r}")
        if density_shift is None:
            density_shift = DENSITY_SHIFT[density_activation]
        self.density_shift, self.density_scale, self.init_std = density_shift, density_scale, init_std
        self.density_activation = density_activation
        self._volume: tuple | None = None  # density_volume's cache: (factors' key, volume)
        self._edits = 0  # bumped by `touch` (fused Adam leaves the version counters as they are)
        self._tables: tuple | None = None  # color_from_codes' cache: (factors' key, VmTables)
        self.density_planes, self.density_lines = self._factors(self.density_rank)
        if has_color:
            self.app_planes, self.app_lines = self._factors(self.app_rank)
            self.basis = nn.Linear(sum(self.app_rank), app_dim, bias=False)
            n_in = app_dim + 2 * feat_freqs * app_dim
            if self.view_dependent:
                n_in += 3 + 2 * view_freqs * 3
            self.mlp = nn.Sequential(
                nn.Linear(n_in, hidden),
                nn.ReLU(inplace=True),
                nn.Linear(hidden, hidden),
                nn.ReLU(inplace=True),
                nn.Linear(hidden, 3),
            )
            nn.init.constant_(self.mlp[-1].bias, 0.0)
        self.register_load_state_dict_pre_hook(_unstack_factors)

    def _factors(self, ranks: tuple[int, int, int]) -> tuple[nn.ParameterList, nn.ParameterList]:
        """Planes (xy, xz, yz) [1, C_m, R, R] and lines (z, y, x) [1, C_m, R, 1], C_m = ranks[m]."""
        r, std = self.resolution, self.init_std
        return (
            nn.ParameterList([std * torch.randn(1, c, r, r) for c in ranks]),
            nn.ParameterList([std * torch.randn(1, c, r, 1) for c in ranks]),
        )

    def normalize(self, x: Tensor) -> Tensor:
        """Scene frame [N, 3] -> box coordinates in [-1, 1]^3 (outside the box: beyond +-1)."""
        return (x - self.aabb[0]) * (2.0 / (self.aabb[1] - self.aabb[0])) - 1.0

    def _inside(self, xn: Tensor) -> Tensor:
        return (xn.abs() <= 1.0).all(dim=-1)

    def density(self, x: Tensor) -> Tensor:
        check_points(x)
        xn = self.normalize(x)
        f = sum(p.sum(0) for p in _plane_features(self.density_planes, self.density_lines, xn.clamp(-1, 1)))  # [N]
        return torch.where(self._inside(xn), self._sigma(f), torch.zeros_like(f))

    def _sigma(self, f: Tensor) -> Tensor:
        """The density factors' sum f [N] -> sigma [N] (module doc)."""
        x = (f + self.density_shift).clamp(max=1e4)
        return self.density_scale * (F.relu(x) if self.density_activation == "relu" else F.softplus(x))

    def density_volume(self) -> Tensor:
        """The density factors' sum at every grid node, [1, 1, R, R, R] indexed (z, y, x) as `F.grid_sample` reads
        a volume: a plane's bilinear interpolation times a line's linear one is the trilinear interpolation of their
        products at the nodes, so trilinear sampling of this volume gives `density`'s factor sum exactly (up to
        float rounding) from 8 values a point instead of 3 x (4 + 2) x density_rank. Kept until the factors
        change (their version counters: optimizer steps, loads and upsampling all bump or replace them)."""
        key = self._cache_key([*self.density_planes, *self.density_lines])
        if self._volume is None or self._volume[0] != key:
            self._volume = (key, vm_node_volume(self.density_planes, self.density_lines))
        return self._volume[1]

    def touch(self) -> None:
        """The factors changed in place behind their version counters (a fused Adam step): rebuild the density volume
        and the appearance tables (without it an evaluation reads stale ones: docs/MEASUREMENTS.md, "Fields")."""
        self._edits += 1

    @torch.no_grad()
    def density_inference(self, x: Tensor) -> Tensor:
        """`density` through `density_volume` (no gradient): the renderers' sigma_fn at inference."""
        check_points(x)
        xn = self.normalize(x)
        grid = xn.clamp(-1, 1)[None, :, None, None, :].to(self.density_planes[0].dtype)  # [1, N, 1, 1, 3] (x, y, z)
        f = F.grid_sample(self.density_volume(), grid, mode="bilinear", align_corners=True).reshape(-1).to(x.dtype)
        return torch.where(self._inside(xn), self._sigma(f), torch.zeros_like(f))

    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        check_points(x)
        if not self.has_color:
            raise ValueError("this field is density-only (has_color=False)")
        xn = self.normalize(x).clamp(-1, 1)
        f = torch.cat(_plane_features(self.app_planes, self.app_lines, xn))  # [sum(app_rank), N]
        inputs = self._feature_inputs(self.basis(f.T))  # [N, app_dim (1 + 2 feat_freqs)]
        if self.view_dependent:
            if d is None:
                raise ValueError("this field is view dependent: pass directions d [N, 3]")
            inputs = torch.cat([inputs, d, positional_encoding(d, self.view_freqs, include_input=False)], dim=-1)
        return torch.sigmoid(self.mlp(inputs))

    @torch.no_grad()
    def color_inference(self, x: Tensor, d: Tensor | None) -> Tensor:
        """`color` through `direction_codes` and `color_from_codes` (no gradient): the same values up to float
        rounding. The renderers take the two parts (`radiance.render.RayColour`) at inference."""
        if not self.has_color:
            raise ValueError("this field is density-only (has_color=False)")
        if self.view_dependent and d is None:
            raise ValueError("this field is view dependent: pass directions d [N, 3]")
        codes = self.direction_codes(d) if self.view_dependent else None
        return self.color_from_codes(x, codes)

    @torch.no_grad()
    def direction_codes(self, d: Tensor) -> Tensor:
        """View directions d [R, 3] -> their term of the colour MLP's first layer (with its bias), [R, hidden]:
        what `color_from_codes` adds to each sample of the ray (`radiance.render.RayColour`)."""
        first = self.mlp[0]
        n_dir = 3 + 2 * self.view_freqs * 3
        enc = torch.cat([d, positional_encoding(d, self.view_freqs, include_input=False)], dim=-1).to(first.weight)
        return F.linear(enc, first.weight[:, -n_dir:], first.bias)  # [R, hidden]

    @torch.no_grad()
    def color_from_codes(self, x: Tensor, codes: Tensor | None) -> Tensor:
        """`color` at x [K, 3] given each sample's `direction_codes` [K, hidden] (None: a view-independent field),
        the appearance features from channels-last tables (`VmTables`, kept until the factors change, as
        `density_volume` is) where they fit; no gradient."""
        check_points(x)
        if not self.has_color:
            raise ValueError("this field is density-only (has_color=False)")
        if (codes is None) == self.view_dependent:
            raise ValueError(
                f"expected direction codes for a view-dependent field and None otherwise (view_dependent "
                f"{self.view_dependent}), got {'None' if codes is None else tuple(codes.shape)}"
            )
        dtype = self.app_planes[0].dtype
        xn = self.normalize(x).clamp(-1, 1).to(dtype)
        if VmTables.fits(self.app_planes, self.app_lines):
            f = self._app_tables().features(xn)  # [K, sum(app_rank)]
        else:  # a component count per plane: grid_sample (docs/TRAINING.md, "Inference")
            f = torch.cat(_plane_features(self.app_planes, self.app_lines, xn)).T
        inputs = self._feature_inputs(self.basis(f))  # [K, app_dim (1 + 2 feat_freqs)]
        first = self.mlp[0]
        if codes is None:
            h = first(inputs)
        else:  # the first layer's feature columns; the direction columns and the bias are in the codes
            h = F.linear(inputs, first.weight[:, : inputs.shape[1]]) + codes.to(dtype)
        return torch.sigmoid(self.mlp[1:](h)).to(x.dtype)

    def _feature_inputs(self, feat: Tensor) -> Tensor:
        """Appearance features after the basis, feat [N, app_dim] -> the colour MLP's inputs before the direction's:
        feat and, with feat_freqs, its encoding."""
        if not self.feat_freqs:
            return feat
        return torch.cat([feat, positional_encoding(feat, self.feat_freqs, include_input=False)], dim=-1)

    def _cache_key(self, factors: list[Tensor]) -> tuple:
        """What a cache built from `factors` depends on: their storage, version counters and shapes, `touch`'s
        count, dtype and device."""
        return (factors_key(factors), self._edits)

    def _app_tables(self) -> VmTables:
        key = self._cache_key([*self.app_planes, *self.app_lines])
        if self._tables is None or self._tables[0] != key:
            with torch.no_grad():
                self._tables = (key, VmTables.build(self.app_planes, self.app_lines))
        return self._tables[1]

    def grid_parameters(self) -> list[nn.Parameter]:
        groups = ["density_planes", "density_lines"] + (["app_planes", "app_lines"] if self.has_color else [])
        return [p for g in groups for p in getattr(self, g)]

    def param_groups(self, lr: float) -> list[dict]:
        """Grids at `lr`, the basis and MLP at lr / 20 (TensoRF: 0.02 and 0.001)."""
        grids = self.grid_parameters()
        ids = {id(p) for p in grids}
        rest = [p for p in self.parameters() if id(p) not in ids]
        groups = [{"params": grids, "lr": lr, "lr_scale": 1.0}]
        if rest:
            groups.append({"params": rest, "lr": lr / 20.0, "lr_scale": 1.0 / 20.0})
        return groups

    def density_l1(self) -> Tensor:
        """Mean absolute value of the density factors, texel-weighted over planes and over lines (TensoRF's L1
        sparsity prior)."""
        return _mean_abs(self.density_planes) + _mean_abs(self.density_lines)

    def _tv_planes(self) -> list[Tensor]:
        return [*self.density_planes, *(self.app_planes if self.has_color else [])]

    def tv(self) -> Tensor:
        """TensoRF's total-variation prior on the planes (its `TVLoss`): for each factor group, 2 x (mean squared
        difference of neighbouring texels along H + along W) per plane, summed over the three planes; density plus
        appearance (when present). Smooths the factors, which removes the streaks and floaters a VM field paints
        into sparsely seen space (TensoRF applies it to real captures). Every texel: the plain twin of
        `add_tv_grad_`."""
        return sum(_plane_tv(p) for p in self._tv_planes())

    def add_tv_grad_(self, weight: float, texels: int, gen: torch.Generator | None = None) -> float:
        """Add weight x the gradient of an unbiased `tv` estimate from `texels` random neighbour pairs per plane to
        the planes' .grad (call after backward, before the optimizer step); returns the estimate. At 256^2 the
        full `tv` costs about as much as a training step, this a few milliseconds."""
        total = 0.0
        for plane in self._tv_planes():
            total += add_plane_tv_grad_(plane, tv_pairs(plane.shape, texels, gen, plane.device), weight)
        return total

    @torch.no_grad()
    def upsample(self, resolution: int) -> None:
        """Resample every plane and line to `resolution` per axis (new Parameters: rebuild the optimizer)."""
        r = int(resolution)
        for kind in ("density", "app") if self.has_color else ("density",):
            planes, lines = getattr(self, f"{kind}_planes"), getattr(self, f"{kind}_lines")
            for m in range(3):
                for factors, size in ((planes, (r, r)), (lines, (r, 1))):
                    grown = F.interpolate(factors[m].data, size=size, mode="bilinear", align_corners=True)
                    factors[m] = nn.Parameter(grown)
        self.resolution = r

    def config(self) -> dict:
        return {
            "kind": "fast",
            "aabb": self.aabb.tolist(),
            "resolution": self.resolution,
            "density_rank": _uniform(self.density_rank),
            "app_rank": _uniform(self.app_rank),
            "app_dim": self.app_dim,
            "hidden": self.hidden,
            "view_freqs": self.view_freqs,
            "feat_freqs": self.feat_freqs,
            "has_color": self.has_color,
            "view_dependent": self.view_dependent,
            "density_shift": self.density_shift,
            "density_scale": self.density_scale,
            "density_activation": self.density_activation,
            "init_std": self.init_std,
        }


FACTOR_NAMES = ("density_planes", "density_lines", "app_planes", "app_lines")


def _unstack_factors(module: nn.Module, state: dict, prefix: str, *args) -> None:
    """A checkpoint from before per-plane factors holds each group as one stacked tensor [3, C, R, R] (lines
    [3, C, R, 1]): split it into the three [1, C, R, R] tensors the field holds now."""
    for name in FACTOR_NAMES:
        stacked = state.pop(prefix + name, None)
        if stacked is not None:
            for m in range(3):
                state[f"{prefix}{name}.{m}"] = stacked[m : m + 1]


def has_stacked_factors(field_state: dict) -> bool:
    """A field state dict saved before per-plane factors (`_unstack_factors` reads it)."""
    return any(name in field_state for name in FACTOR_NAMES)


def _split(value: Tensor, m: int) -> Tensor:
    """Plane m's share of a stacked factor's Adam entry: its slice of a moment, its own copy of the step count (fused
    Adam counts each parameter's steps in place: a shared count would advance three times a step)."""
    return value[m : m + 1].clone() if value.dim() > 0 else value.clone()


def unstack_adam_state(opt_state: dict) -> dict:
    """An Adam state dict saved with stacked factors -> today's: the grid group's (the first) parameters, each a
    stacked [3, ...] factor in `grid_parameters`' order, become three [1, ...] entries each; every later parameter is
    renumbered. The moments are split exactly as `_unstack_factors` splits the factors."""
    groups, old_state = opt_state["param_groups"], opt_state["state"]
    new_groups, new_state, index = [], {}, 0
    for g, group in enumerate(groups):
        ids = []
        for old in group["params"]:
            entry = old_state.get(old)
            for m in range(3) if g == 0 else range(1):
                if entry is not None:
                    new_state[index] = {k: _split(v, m) if g == 0 else v for k, v in entry.items()}
                ids.append(index)
                index += 1
        new_groups.append({**group, "params": ids})
    return {"state": new_state, "param_groups": new_groups}
