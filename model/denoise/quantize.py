"""Vector quantisation of a latent map (VQ-VAE, van den Oord et al. 2017; VQ-VAE-2, Razavi et al. 2019).

Each latent vector is replaced by its nearest codebook entry; gradients pass straight through to
the encoder (the straight-through estimator), and a commitment loss keeps the encoder's outputs
near the entries they pick. The codebook is updated either by exponential moving averages of the
vectors assigned to each entry (VQ-VAE-2's choice: no codebook loss, steadier on small batches)
or by gradient through a codebook loss. Entries that stop being used are restarted at random
latent vectors of the current batch, and the codebook starts at latent vectors of the first
training batch (not at random vectors, which the encoder's outputs may all lie far from, so that
one entry takes every vector and the others never get one), so a small codebook trained on a
small data set keeps all of its entries in use. Written in plain torch: the operation is a nearest-neighbour search and a few
running averages, and no maintained library offers it as a module with these options.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class QuantizerOutput:
    """``quantized [B, D, H, W]`` (straight-through: its gradient reaches the input), ``loss`` (the
    commitment loss, plus the codebook loss when the codebook is learned by gradient), ``codes
    [B, H, W]`` the chosen entries, ``perplexity`` the effective number of entries the batch used."""

    quantized: torch.Tensor
    loss: torch.Tensor
    codes: torch.Tensor
    perplexity: torch.Tensor


class VectorQuantizer(nn.Module):
    """A codebook of ``entries`` vectors of size ``dim`` for latent maps ``[B, dim, H, W]``.

    ``ema`` updates the codebook by moving averages with ``decay`` (Laplace-smoothed cluster sizes,
    as in VQ-VAE-2); otherwise the codebook is a parameter trained through the codebook loss.
    ``commitment`` weighs ``||z - sg(e)||^2``. During training, entries whose recent use (a moving
    average over about the last ten batches) falls under ``restart_below`` of an even share of the
    batch are moved onto random latent vectors of the batch.
    """

    def __init__(self, entries: int, dim: int, *, commitment: float = 0.25, ema: bool = True, decay: float = 0.99,
                 restart_below: float = 0.01, use_decay: float = 0.9, eps: float = 1e-5):
        super().__init__()
        if entries < 1 or dim < 1:
            raise ValueError(f"a codebook needs at least one entry of at least one dimension, got {entries} x {dim}")
        self.entries, self.dim = entries, dim
        self.commitment, self.ema, self.decay, self.eps = commitment, ema, decay, eps
        self.restart_below, self.use_decay = restart_below, use_decay
        codebook = torch.randn(entries, dim) / dim**0.5
        if ema:
            self.register_buffer("codebook", codebook)
            self.register_buffer("cluster_size", torch.ones(entries))
            self.register_buffer("cluster_sum", codebook.clone())
        else:
            self.codebook = nn.Parameter(codebook)
        self.register_buffer("recent_use", torch.ones(entries))  # share of an even split, recent batches
        self.register_buffer("initialised", torch.tensor(False))

    def nearest(self, flat: torch.Tensor) -> torch.Tensor:
        """Index ``[N]`` of the nearest entry to each vector of ``flat [N, D]`` (squared Euclidean)."""
        distance = flat.pow(2).sum(1, keepdim=True) - 2 * flat @ self.codebook.t() + self.codebook.pow(2).sum(1)[None]
        return distance.argmin(dim=1)

    def forward(self, z: torch.Tensor) -> QuantizerOutput:
        batch, dim, height, width = z.shape
        if dim != self.dim:
            raise ValueError(f"latent map has {dim} channels, the codebook {self.dim}")
        flat = z.permute(0, 2, 3, 1).reshape(-1, dim)
        if self.training and not bool(self.initialised):
            self._start_from(flat.detach())
        codes = self.nearest(flat.detach())
        one_hot = F.one_hot(codes, self.entries).type(flat.dtype)
        if self.training:
            self._track_use(flat.detach(), one_hot)
        chosen = F.embedding(codes, self.codebook)
        loss = self.commitment * F.mse_loss(flat, chosen.detach())
        if not self.ema:
            loss = loss + F.mse_loss(chosen, flat.detach())
        quantized = flat + (chosen - flat).detach()  # straight-through: identity gradient to z
        usage = one_hot.mean(0)
        perplexity = torch.exp(-(usage * torch.log(usage + 1e-10)).sum())
        return QuantizerOutput(
            quantized.reshape(batch, height, width, dim).permute(0, 3, 1, 2), loss, codes.reshape(batch, height, width), perplexity
        )

    @torch.no_grad()
    def _start_from(self, flat: torch.Tensor) -> None:
        """Entries at distinct random vectors of ``flat [N, D]`` (repeated when N < entries)."""
        order = torch.randperm(flat.shape[0], device=flat.device)
        picks = flat[order.repeat(self.entries // flat.shape[0] + 1)[: self.entries]]
        self.codebook.copy_(picks)
        if self.ema:
            self.cluster_sum.copy_(picks * self.cluster_size[:, None])
        self.initialised.fill_(True)

    @torch.no_grad()
    def _track_use(self, flat: torch.Tensor, one_hot: torch.Tensor) -> None:
        """Recent use of each entry; with ``ema`` the moving-average codebook update; restarts."""
        counts = one_hot.sum(0)
        self.recent_use.mul_(self.use_decay).add_(counts * (self.entries / flat.shape[0]), alpha=1 - self.use_decay)
        if self.ema:
            self.cluster_size.mul_(self.decay).add_(counts, alpha=1 - self.decay)
            self.cluster_sum.mul_(self.decay).add_(one_hot.t() @ flat, alpha=1 - self.decay)
            total = self.cluster_size.sum()
            smoothed = (self.cluster_size + self.eps) / (total + self.entries * self.eps) * total
            self.codebook.copy_(self.cluster_sum / smoothed[:, None])
        dead = (self.recent_use < self.restart_below).nonzero().squeeze(1)
        if dead.numel():
            picks = flat[torch.randint(0, flat.shape[0], (dead.numel(),), device=flat.device)]
            self.codebook[dead] = picks
            self.recent_use[dead] = 1.0
            if self.ema:
                self.cluster_size[dead] = 1.0
                self.cluster_sum[dead] = picks
