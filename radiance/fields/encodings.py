"""Input encodings for fields.

`positional_encoding` is the NeRF paper's gamma(p) = (p, sin(2^0 pi p), cos(2^0 pi p), ...,
sin(2^(L-1) pi p), cos(2^(L-1) pi p)), identity included (as the paper's code does). The reference
implementation multiplies by 2^k without pi; we follow the code (frequencies 2^k), which the paper's
released models use.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["positional_encoding", "encoded_size"]


def encoded_size(dims: int, n_freqs: int, include_input: bool = True) -> int:
    """Output width of `positional_encoding` for `dims` inputs and `n_freqs` frequencies."""
    return dims * (2 * n_freqs + int(include_input))


def positional_encoding(x: Tensor, n_freqs: int, include_input: bool = True) -> Tensor:
    """x [N, D] -> [N, D * (2 L + 1)]: (x, sin(2^k x), cos(2^k x) for k < L), grouped per frequency."""
    freqs = 2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)  # [L]
    xb = (x[:, None, :] * freqs[None, :, None]).reshape(x.shape[0], n_freqs * x.shape[1])  # [N, L * D]
    parts = [x] if include_input else []
    parts += [torch.sin(xb), torch.cos(xb)]
    return torch.cat(parts, dim=-1)
