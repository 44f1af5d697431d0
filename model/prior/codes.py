"""What a prior does with codes: generate an instance's NeRF, swap shape and colour between
instances, and give a generated NeRF its occupancy grid from its own density.

Every function runs the hypernetwork once and returns batch-1 field parameters.
"""

from __future__ import annotations

import torch

from model.nerf.fields import Field, FieldParams, world_density
from model.nerf.occupancy import OccupancyGrid, grid_from_density
from model.nerf.scene import SceneBox
from model.prior.hypernet import HyperNetwork


def _device(net: HyperNetwork) -> torch.device:
    return next(net.parameters()).device


@torch.no_grad()
def generate(net: HyperNetwork, instance: int) -> FieldParams:
    """The NeRF of a training instance's own codes."""
    return net(torch.tensor([instance], device=_device(net)))


@torch.no_grad()
def swap_codes(net: HyperNetwork, shape_instance: int, color_instance: int) -> FieldParams:
    """The NeRF of one instance's shape code with another instance's colour code."""
    device = _device(net)
    shape_code, _ = net.codes(torch.tensor([shape_instance], device=device))
    _, color_code = net.codes(torch.tensor([color_instance], device=device))
    return net.params_from_codes(shape_code, color_code)


@torch.no_grad()
def generated_grid(params: FieldParams, field_cfg: Field, scene: SceneBox, resolution: int = 64, samples_per_cell: int = 2, seed: int = 0) -> OccupancyGrid:
    """The occupancy grid of a generated NeRF from its own density (what the service caches with
    it); the jitter is seeded, so the same NeRF always gets the same grid."""
    device = next(iter(params.values())).device
    generator = torch.Generator(device=device).manual_seed(seed)
    return grid_from_density(
        world_density(params, field_cfg, scene), scene, resolution=resolution, samples_per_cell=samples_per_cell, generator=generator, device=device
    )
