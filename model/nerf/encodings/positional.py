"""NeRF's sinusoidal positional encoding (Mildenhall et al. 2020), used by the positional field."""

from __future__ import annotations

import math

import torch


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """NeRF's encoding ``[x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^{F-1} pi x), cos(2^{F-1} pi x)]``.

    ``x [..., D]`` -> ``[..., D * (1 + 2 F)]``; the sines and cosines of each frequency are grouped
    (all ``D`` sines, then all ``D`` cosines), as in NeRF's ``embed_fn``.
    """
    if frequencies <= 0:
        return x
    scales = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * math.pi  # [F]
    angles = x[..., None, :] * scales[:, None]  # [..., F, D]
    parts = torch.stack([torch.sin(angles), torch.cos(angles)], dim=-2)  # [..., F, 2, D]
    return torch.cat([x, parts.flatten(-3)], dim=-1)


def encoded_dim(dim: int, frequencies: int) -> int:
    return dim * (1 + 2 * max(frequencies, 0))
