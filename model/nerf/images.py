"""Images: compositing straight-alpha RGBA over a background, and PNG output (Pillow)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """``[H, W, C]`` floats in [0, 1] -> uint8 array (rounded, clipped)."""
    return (image.detach().float().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def save_png(path: Path, image: torch.Tensor) -> None:
    Image.fromarray(to_uint8(image)).save(path)


def composite_over(rgba: torch.Tensor, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """Straight-alpha RGBA ``[..., 4]`` over a constant background -> RGB ``[..., 3]``."""
    bg = torch.tensor(background, dtype=rgba.dtype, device=rgba.device)
    return rgba[..., :3] * rgba[..., 3:] + bg * (1 - rgba[..., 3:])
