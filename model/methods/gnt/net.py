"""GNT's network (Wang et al., ICLR 2023), cut to CPU size: a view transformer over each sample's K source views, a
ray transformer over each ray's samples, and an attention read-out in place of the volume-rendering sum.

Shapes: R rays, S samples a ray, K source views a ray, C feature channels (+4: the source pixel's premultiplied
rgb and alpha), D the token width.
- View transformer (per sample, across its K views): GNT's subtraction attention. Each view's key and value come
  from its features, a positional code of the ray difference (the target direction minus the source's, and their
  dot product) is added to both; the weights softmax(MLP(q - k + pos)) are per channel and per view, over the views
  that see the sample only (`seen`). The first block's query is the masked max over views of the features plus an
  MLP of their mean and variance (IBRNet's explicit cue: views that agree at a sample suggest a surface there; added
  because our pretraining is thousands of steps, not GNT's 250k); later blocks' queries are the tokens.
- Ray transformer (per ray, across its S samples): pre-norm multi-head self-attention plus a feed-forward, with a
  sinusoidal code of each sample's position along the ray (0 at the ray's near end, 1 at its far end).
- Read-out: one logit a sample, softmax over the ray: coverage (alpha) from the weighted token; the same weights
  give the depth (GNT reads depth from the ray transformer's attention the same way) and pool the samples' colours.
  A sample's colour (`readout`):
  - `direct`: an MLP of the token (GNT's linear read-out);
  - `blend` (default): IBRNet's colour blending, the source pixels' colours at the sample (unpremultiplied) weighted
    by a softmax over the views that see it, plus one more entry, the token's own colour, for what no source shows.
    A network trained for thousands of steps, not GNT's 250k, has not learned to copy colour through its tokens;
    blending copies it by construction and leaves the network to choose whom to copy.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from nerfpipe.model.methods.gnt.features import make_extractor

__all__ = ["GntNet", "masked_softmax", "READOUTS", "stored_config", "unpremultiply"]

READOUTS = ("blend", "direct")
"""How a sample's colour is read (module doc)."""


def masked_softmax(logits: Tensor, mask: Tensor, dim: int) -> Tensor:
    """softmax of logits over `dim` among mask's True entries (broadcast); 0 where a slice has none.
    A masked entry's exp(finfo.min - max) is exactly 0 beside any unmasked one, so only the slices without one
    (uniform weights) need zeroing: a multiply by `mask.any(dim)`, not by the whole mask and a renormalisation."""
    w = torch.softmax(logits.masked_fill(~mask, torch.finfo(logits.dtype).min), dim=dim)
    return w * mask.any(dim=dim, keepdim=True)


def unpremultiply(rgba: Tensor) -> Tensor:
    """Source pixels [..., 4] (colour premultiplied by alpha, alpha) -> colour [..., 3]; 0 where alpha is 0 (data,
    not learned: the quotient carries no gradient to the network, so no epsilon guards it beyond the zero)."""
    a = rgba[..., 3:]
    some = a > 0
    return torch.where(some, rgba[..., :3] / torch.where(some, a, torch.ones_like(a)), 0.0).clamp(0, 1)


def stored_config(config: dict) -> dict:
    """A network configuration as stored in a weights file or checkpoint, completed: one written before `readout`
    existed read its colour out directly."""
    return {"readout": "direct", **config}


def _mlp(d_in: int, d_hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d_hidden), nn.ReLU(), nn.Linear(d_hidden, d_out))


class _ViewBlock(nn.Module):
    def __init__(self, d: int):
        super().__init__()
        self.key, self.value, self.query = nn.Linear(d, d), nn.Linear(d, d), nn.Linear(d, d)
        self.attn = _mlp(d, d, d)
        self.out = nn.Linear(d, d)
        self.norm = nn.LayerNorm(d)
        self.ff = _mlp(d, 2 * d, d)

    def forward(self, token: Tensor, views: Tensor, pos: Tensor, seen: Tensor) -> Tensor:
        """token [R, S, D], views [R, S, K, D], pos [R, S, K, D], seen [R, S, K] -> token [R, S, D]."""
        q = self.query(token)[:, :, None]
        w = masked_softmax(self.attn(q - self.key(views) + pos), seen[..., None], dim=2)  # [R, S, K, D]
        token = token + self.out((w * (self.value(views) + pos)).sum(2))
        return token + self.ff(self.norm(token))


class _RayBlock(nn.Module):
    def __init__(self, d: int, heads: int):
        super().__init__()
        self.norm_a, self.norm_b = nn.LayerNorm(d), nn.LayerNorm(d)
        self.attn = nn.MultiheadAttention(d, heads, batch_first=True)
        self.ff = _mlp(d, 2 * d, d)

    def forward(self, token: Tensor) -> Tensor:  # [R, S, D]
        x = self.norm_a(token)
        token = token + self.attn(x, x, x, need_weights=False)[0]
        return token + self.ff(self.norm_b(token))


class GntNet(nn.Module):
    """Extractor + view and ray transformers + read-out (module doc). `config()` rebuilds it."""

    def __init__(
        self,
        *,
        extractor: str = "shallow",
        channels: int = 32,
        width: int = 32,
        blocks: int = 2,
        heads: int = 4,
        frequencies: int = 6,
        readout: str = "blend",
    ):
        super().__init__()
        if readout not in READOUTS:
            raise ValueError(f"readout: expected one of {READOUTS}, got {readout!r}")
        self._config = dict(
            extractor=extractor,
            channels=channels,
            width=width,
            blocks=blocks,
            heads=heads,
            frequencies=frequencies,
            readout=readout,
        )
        self.readout = readout
        self.extractor = make_extractor(extractor, channels)
        self.stride = self.extractor.stride
        self.frequencies = frequencies
        self.embed = nn.Linear(channels + 4, width)
        self.stats = _mlp(2 * width, width, width)
        self.pos = _mlp(4, width, width)
        self.ray_pos = nn.Linear(2 * frequencies + 1, width)
        self.view_blocks = nn.ModuleList([_ViewBlock(width) for _ in range(blocks)])
        self.ray_blocks = nn.ModuleList([_RayBlock(width, heads) for _ in range(blocks)])
        self.norm = nn.LayerNorm(width)
        self.logit = nn.Linear(width, 1)
        self.rgb = _mlp(width, width, 3)
        self.alpha = nn.Linear(width, 1)
        if readout == "blend":
            self.blend = _mlp(width, width, 1)  # a view's blending logit, from its token, its code and the sample's
            self.own = nn.Linear(width, 1)  # the logit of the token's own colour

    def config(self) -> dict:
        return dict(self._config)

    @staticmethod
    def from_config(config: dict) -> GntNet:
        """The network a stored configuration names (`stored_config`)."""
        return GntNet(**stored_config(config))

    def features(self, images: Tensor) -> Tensor:
        """Source images [V, 4, H, W] -> feature maps [V, C, H / stride, W / stride]."""
        return self.extractor(images)

    def forward(self, views: Tensor, ray_diff: Tensor, seen: Tensor, t01: Tensor) -> dict[str, Tensor]:
        """views [R, S, K, C + 4] (features, then the source pixel's rgba), ray_diff [R, S, K, 4], seen [R, S, K]
        (bool), t01 [R, S] (position along the ray in [0, 1]) -> dict(rgb [R, 3], alpha [R], weights [R, S])."""
        if views.shape[-1] < 4:
            raise ValueError(f"expected views [R, S, K, C + 4] ending with the source pixel's rgba, got {views.shape}")
        x = self.embed(views)  # [R, S, K, D]
        pos = self.pos(ray_diff)
        m = seen[..., None]
        token = x.masked_fill(~m, torch.finfo(x.dtype).min).amax(2)  # masked max over the views: [R, S, D]
        token = torch.where(seen.any(2, keepdim=True), token, torch.zeros_like(token))
        count = m.sum(2).clamp_min(1)  # [R, S, 1]
        mean = (x * m).sum(2) / count
        var = (((x - mean[:, :, None]) * m) ** 2).sum(2) / count  # the views' agreement (IBRNet's cue for a surface)
        token = token + self.stats(torch.cat([mean, var], dim=-1))
        freq = (2.0 ** torch.arange(self.frequencies, device=t01.device, dtype=t01.dtype)) * math.pi
        code = torch.cat([t01[..., None], torch.sin(t01[..., None] * freq), torch.cos(t01[..., None] * freq)], -1)
        ray_code = self.ray_pos(code)  # [R, S, D]
        for view_block, ray_block in zip(self.view_blocks, self.ray_blocks, strict=True):
            token = view_block(token, x, pos, seen)
            token = ray_block(token + ray_code)
        token = self.norm(token)
        weights = torch.softmax(self.logit(token)[..., 0], dim=1)  # [R, S]
        pooled = (weights[..., None] * token).sum(1)  # [R, D]
        if self.readout == "direct":
            rgb = torch.sigmoid(self.rgb(pooled))
        else:
            rgb = (weights[..., None] * self._blend(token, x, pos, seen, views[..., -4:])).sum(1)
        return {"rgb": rgb, "alpha": torch.sigmoid(self.alpha(pooled))[..., 0], "weights": weights}

    def _blend(self, token: Tensor, x: Tensor, pos: Tensor, seen: Tensor, rgba: Tensor) -> Tensor:
        """Each sample's colour [R, S, 3]: the seen views' colours and the token's own, softmax-weighted (module doc).
        token [R, S, D], x and pos [R, S, K, D], seen [R, S, K], rgba [R, S, K, 4] (premultiplied)."""
        logits = torch.cat([self.blend(x + pos + token[:, :, None])[..., 0], self.own(token)], dim=-1)  # [R, S, K+1]
        mask = torch.cat([seen, torch.ones_like(seen[..., :1])], dim=-1)
        w = masked_softmax(logits, mask, dim=-1)
        colours = torch.cat([unpremultiply(rgba), torch.sigmoid(self.rgb(token))[:, :, None]], dim=2)  # [R, S, K+1, 3]
        return (w[..., None] * colours).sum(2)
