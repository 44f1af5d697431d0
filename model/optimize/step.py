"""The one photometric step every optimisation shares: per-object fits, prior training, and later
test-time optimisation and finetuning.

A batch of rays with straight-alpha RGBA targets is rendered over a background and scored by its
mean squared error. Images with alpha are trained over a random background per ray, so opacity is
learned (the target is composited over the same background); images without alpha are trained
against their own pixels over the render's fixed background. Optimisers are Adam with an
exponential learning-rate decay to ``final_lr_factor`` of the start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from model.nerf.fields import Field, FieldParams
from model.nerf.occupancy import OccupancyGrid
from model.nerf.renderer import RenderConfig, render_rays
from model.nerf.scene import SceneBox


@dataclass
class RayBatch:
    """World rays ``origins``, ``directions [R, 3]`` and their straight-alpha targets ``rgba [R, 4]``."""

    origins: torch.Tensor
    directions: torch.Tensor
    rgba: torch.Tensor

    def __len__(self) -> int:
        return self.origins.shape[0]


def photometric_loss(
    params: FieldParams,
    field_cfg: Field,
    batch: RayBatch,
    cfg: RenderConfig,
    *,
    scene: SceneBox,
    grid: OccupancyGrid | None,
    random_background: bool,
    generator: torch.Generator,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Mean squared error of the rendered batch against its targets, and the render's outputs.

    With ``random_background`` each ray gets a uniform random background colour, behind both the
    render and the target; otherwise the render's fixed ``cfg.background`` is used.
    """
    device = batch.origins.device
    rays = len(batch)
    if random_background:
        background = torch.rand(rays, 3, device=device, generator=generator)
    else:
        background = torch.tensor(cfg.background, device=device).expand(rays, 3)
    alpha = batch.rgba[:, 3:]
    target = batch.rgba[:, :3] * alpha + background * (1 - alpha)
    out = render_rays(
        params, field_cfg, batch.origins, batch.directions, cfg, scene=scene, grid=grid, background=background, jitter=True, generator=generator
    )
    return torch.mean((out["rgb"] - target) ** 2), out


def adam_with_decay(param_groups, *, lr: float, steps: int, final_lr_factor: float, betas=(0.9, 0.99), fused: bool = False):
    """Adam (eps 1e-15, as InstantNGP) and a per-step exponential decay reaching ``final_lr_factor``."""
    optimizer = torch.optim.Adam(param_groups, lr=lr, betas=betas, eps=1e-15, fused=fused)
    decay = math.log(final_lr_factor) / max(steps, 1)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: math.exp(decay * step))
    return optimizer, scheduler


def mse_to_psnr(mse: float) -> float:
    return -10 * math.log10(max(mse, 1e-10))
