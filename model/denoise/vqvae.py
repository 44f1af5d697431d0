"""The image-to-image denoiser: a VQ-VAE-2-style network with two levels of quantised latents
(paper section 3.1, step 2), in plain torch (``torch.nn`` convolutions and
``model.denoise.quantize``; VQ-VAE-2 has no maintained pip package, and the network is a few
dozen layers).

As in VQ-VAE-2 (Razavi et al. 2019): a bottom encoder brings the image down 4x, a top encoder a
further 2x; the top latents are quantised with their own codebook and decoded back to the bottom
resolution, where they condition the quantisation of the bottom latents; the decoder takes both
quantised maps (the top one upsampled) back to the image. Residual blocks, straight-through
gradients, commitment losses and moving-average codebooks are VQ-VAE-2's.

What is changed, and why:

* **It denoises instead of reconstructing.** Trained on (render of the prior's NeRF, ground
  truth) pairs with an L2 loss, as the paper does; there is no autoregressive prior over the
  codes, since nothing is sampled from it.
* **The decoder predicts a correction, not the image.** Its output is added to the input in
  logit space: ``out = sigmoid(logit(x) + decoder(...))``, with the decoder's last layer starting
  at zero, so an untrained denoiser is the identity. A two-level code map of 16x16 and 32x32
  entries cannot carry a 128x128 image's detail; it can carry what is wrong with it (haze, soft
  silhouettes, washed-out colour), and the input carries the rest.
* **A full-resolution skip path.** A shallow convolutional path from the input joins the decoder
  at full resolution (``skip_channels``; 0 gives VQ-VAE-2's decoder), so a correction can be
  placed at the pixel where it belongs. Measured on this project's chair prior (612 pairs, 600
  steps, 16 held-out views): from the quantised latents alone the denoiser learned nothing
  (32.57 -> 32.56 dB full, 23.16 -> 23.17 dB foreground); with the skip path it cleaned the
  background (33.09 dB full) but blurred the object (22.35 dB foreground). What reaches beyond a
  few pixels still has to pass through the codebooks.
* **RGBA in, RGBA out.** The input is the render over white plus its opacity, and the output an
  alpha and a colour over white, so the denoised views keep masks: finetuning on them can remove
  density the ground truth does not have instead of painting it white.
* **Sized for 128x128 on 2 CPU cores**: 64 hidden channels (VQ-VAE-2: 128), residual blocks of
  32, codebooks of 256 entries of 32 dimensions (512 of 64), one residual block per stage by
  default (2). Images of any size are padded to a multiple of 8 (the top level's stride) and
  cropped back.
* **Unused codebook entries are restarted** at random latent vectors (see ``quantize``): with a
  few thousand training images a codebook otherwise keeps many dead entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from model.denoise.quantize import VectorQuantizer

# the top level's total stride: inputs are padded to a multiple of it
STRIDE = 8
# inputs are clamped this far inside (0, 1) before the logit, so white backgrounds stay finite
LOGIT_EPS = 1e-3


@dataclass
class DenoiserConfig:
    """Sizes of the denoiser (``model.nerf.config`` serialises it)."""

    hidden: int = 64
    residual_hidden: int = 32
    residual_blocks: int = 1
    embed_dim: int = 32
    top_entries: int = 256
    bottom_entries: int = 256
    commitment: float = 0.25
    ema: bool = True
    ema_decay: float = 0.99
    skip_channels: int = 16  # width of the full-resolution path from the input (0: none, VQ-VAE-2's decoder)

    def __post_init__(self):
        if self.hidden < 2 or self.hidden % 2 or self.residual_hidden < 1 or self.embed_dim < 1 or self.residual_blocks < 0 or self.skip_channels < 0:
            raise ValueError("the denoiser needs an even hidden width >= 2, residual and embedding widths >= 1, "
                             "residual_blocks >= 0 and skip_channels >= 0")


def tiny_config() -> DenoiserConfig:
    """A denoiser small enough for tests (milliseconds per 32x32 image)."""
    return DenoiserConfig(hidden=8, residual_hidden=4, residual_blocks=1, embed_dim=4, top_entries=8, bottom_entries=8, skip_channels=4)


class ResidualBlock(nn.Module):
    def __init__(self, channels: int, hidden: int):
        super().__init__()
        self.body = nn.Sequential(nn.ReLU(), nn.Conv2d(channels, hidden, 3, padding=1), nn.ReLU(), nn.Conv2d(hidden, channels, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


def _stack(cfg: DenoiserConfig) -> list[nn.Module]:
    return [ResidualBlock(cfg.hidden, cfg.residual_hidden) for _ in range(cfg.residual_blocks)] + [nn.ReLU()]


def _encoder(channels_in: int, cfg: DenoiserConfig, stride: int) -> nn.Sequential:
    """Downsample by ``stride`` (4 or 2) with 4x4 stride-2 convolutions, then residual blocks."""
    h = cfg.hidden
    if stride == 4:
        layers = [nn.Conv2d(channels_in, h // 2, 4, 2, 1), nn.ReLU(), nn.Conv2d(h // 2, h, 4, 2, 1), nn.ReLU(), nn.Conv2d(h, h, 3, padding=1)]
    else:
        layers = [nn.Conv2d(channels_in, h // 2, 4, 2, 1), nn.ReLU(), nn.Conv2d(h // 2, h, 3, padding=1)]
    return nn.Sequential(*layers, *_stack(cfg))


def _decoder(channels_in: int, channels_out: int, cfg: DenoiserConfig, stride: int) -> nn.Sequential:
    """Residual blocks, then upsample by ``stride`` (4 or 2) with 4x4 transposed convolutions."""
    h = cfg.hidden
    layers = [nn.Conv2d(channels_in, h, 3, padding=1), *_stack(cfg)]
    if stride == 4:
        layers += [nn.ConvTranspose2d(h, h // 2, 4, 2, 1), nn.ReLU(), nn.ConvTranspose2d(h // 2, channels_out, 4, 2, 1)]
    else:
        layers += [nn.ConvTranspose2d(h, channels_out, 4, 2, 1)]
    return nn.Sequential(*layers)


@dataclass
class DenoiserOutput:
    """``image [B, 4, H, W]``: colour over white (3) and alpha (1) in (0, 1); ``latent_loss`` the
    quantisers' commitment (and codebook) losses; ``perplexity`` (top, bottom) codebook use."""

    image: torch.Tensor
    latent_loss: torch.Tensor
    perplexity: tuple[torch.Tensor, torch.Tensor]


class VQVAE2Denoiser(nn.Module):
    """``forward(x [B, 4, H, W]) -> DenoiserOutput``: ``x`` is a render's colour over white (3
    channels) and opacity (1), in [0, 1]; the output has the same layout."""

    channels = 4

    def __init__(self, cfg: DenoiserConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or DenoiserConfig()
        h, e = cfg.hidden, cfg.embed_dim
        self.encode_bottom = _encoder(self.channels, cfg, stride=4)
        self.encode_top = _encoder(h, cfg, stride=2)
        self.to_top_latent = nn.Conv2d(h, e, 1)
        self.quantize_top = VectorQuantizer(cfg.top_entries, e, commitment=cfg.commitment, ema=cfg.ema, decay=cfg.ema_decay)
        self.decode_top = _decoder(e, e, cfg, stride=2)
        self.to_bottom_latent = nn.Conv2d(e + h, e, 1)
        self.quantize_bottom = VectorQuantizer(cfg.bottom_entries, e, commitment=cfg.commitment, ema=cfg.ema, decay=cfg.ema_decay)
        self.upsample_top = nn.ConvTranspose2d(e, e, 4, 2, 1)
        k = cfg.skip_channels
        self.decode = _decoder(2 * e, h // 2 if k else self.channels, cfg, stride=4)
        if k:
            self.skip = nn.Sequential(nn.Conv2d(self.channels, k, 3, padding=1), nn.ReLU(), nn.Conv2d(k, k, 3, padding=1), nn.ReLU())
            self.head = nn.Sequential(nn.Conv2d(h // 2 + k, k, 3, padding=1), nn.ReLU(), nn.Conv2d(k, self.channels, 3, padding=1))
        for module in self.modules():
            if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
                # He init, zero bias: the image's variation survives a dozen ReLU layers at the start
                # (torch's default init shrinks it about 3x a layer, and the latents then differ so
                # little between positions that one codebook entry takes them all)
                nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
                nn.init.zeros_(module.bias)
        last = self.head[-1] if k else self.decode[-1]
        nn.init.zeros_(last.weight)  # an untrained denoiser returns its input
        nn.init.zeros_(last.bias)

    def forward(self, x: torch.Tensor) -> DenoiserOutput:
        if x.ndim != 4 or x.shape[1] != self.channels:
            raise ValueError(f"the denoiser takes [B, 4, H, W] (colour over white and opacity), got {tuple(x.shape)}")
        height, width = x.shape[-2:]
        pad_h, pad_w = (-height) % STRIDE, (-width) % STRIDE
        # replicate: a white background stays white across the padding
        padded = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate") if pad_h or pad_w else x
        bottom = self.encode_bottom(padded * 2 - 1)
        top = self.quantize_top(self.to_top_latent(self.encode_top(bottom)))
        bottom_q = self.quantize_bottom(self.to_bottom_latent(torch.cat([self.decode_top(top.quantized), bottom], dim=1)))
        decoded = self.decode(torch.cat([self.upsample_top(top.quantized), bottom_q.quantized], dim=1))
        if self.cfg.skip_channels:
            decoded = self.head(torch.cat([F.relu(decoded), self.skip(padded * 2 - 1)], dim=1))
        correction = decoded[..., :height, :width]
        image = torch.sigmoid(torch.logit(x.clamp(LOGIT_EPS, 1 - LOGIT_EPS)) + correction)
        return DenoiserOutput(image, top.loss + bottom_q.loss, (top.perplexity, bottom_q.perplexity))


def to_channels(rgb: torch.Tensor, opacity: torch.Tensor) -> torch.Tensor:
    """A render's ``rgb [V, H, W, 3]`` (over white) and ``opacity [V, H, W]`` -> denoiser input ``[V, 4, H, W]``."""
    return torch.cat([rgb, opacity[..., None]], dim=-1).permute(0, 3, 1, 2).clamp(0, 1)


def rgba_channels(rgba: torch.Tensor) -> torch.Tensor:
    """Straight-alpha ``rgba [V, H, W, 4]`` -> the denoiser's layout ``[V, 4, H, W]`` (colour over white, alpha)."""
    alpha = rgba[..., 3:]
    over_white = rgba[..., :3] * alpha + (1 - alpha)
    return torch.cat([over_white, alpha], dim=-1).permute(0, 3, 1, 2)


def straight_rgba(channels: torch.Tensor, min_alpha: float = 1e-3) -> torch.Tensor:
    """The denoiser's layout ``[V, 4, H, W]`` -> straight-alpha RGBA ``[V, H, W, 4]``.

    The straight colour is ``(over_white - (1 - alpha)) / alpha``; where alpha is under
    ``min_alpha`` the colour does not matter (it is weighted by alpha) and the colour over white
    is kept, so nothing divides by zero.
    """
    over_white, alpha = channels[:, :3].permute(0, 2, 3, 1), channels[:, 3:].permute(0, 2, 3, 1)
    straight = torch.where(alpha > min_alpha, (over_white - (1 - alpha)) / alpha.clamp_min(min_alpha), over_white)
    return torch.cat([straight.clamp(0, 1), alpha], dim=-1)


@torch.no_grad()
def denoise_renders(denoiser: VQVAE2Denoiser, rgb: torch.Tensor, opacity: torch.Tensor, batch: int = 8) -> torch.Tensor:
    """Denoise renders ``rgb [V, H, W, 3]`` (over white) with ``opacity [V, H, W]``; returns
    straight-alpha RGBA ``[V, H, W, 4]`` on the renders' device, in batches of ``batch`` views."""
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or opacity.shape != rgb.shape[:-1]:
        raise ValueError(f"renders must be rgb [V, H, W, 3] with opacity [V, H, W], got {tuple(rgb.shape)} and {tuple(opacity.shape)}")
    if not (torch.isfinite(rgb).all() and torch.isfinite(opacity).all()):
        raise ValueError("the renders contain NaN or infinite values; render the NeRF again before denoising")
    device = next(denoiser.parameters()).device
    was_training = denoiser.training
    denoiser.eval()
    x = to_channels(rgb, opacity).float()
    out = [denoiser(x[i : i + batch].to(device)).image.to(rgb.device) for i in range(0, x.shape[0], batch)]
    denoiser.train(was_training)
    return straight_rgba(torch.cat(out))
