"""Shared fixtures: tiny fields with known densities and a tiny synthetic object to fit."""

from __future__ import annotations

import math

import pytest
import torch

from model.nerf.encodings.hashgrid import HashGridConfig
from model.nerf.fields.hashgrid import FieldConfig, init_params
from model.nerf.rays import Intrinsics, focal_from_fov, pixel_rays

TINY_ENCODING = HashGridConfig(levels=4, log2_table_size=10, features=2, base_resolution=4, finest_resolution=64)


@pytest.fixture
def tiny_field_cfg() -> FieldConfig:
    return FieldConfig(encoding=TINY_ENCODING, hidden=16, geo_features=7, color_hidden=16)


def constant_field(cfg: FieldConfig, sigma: float, logit: float = 0.0) -> dict[str, torch.Tensor]:
    """Parameters whose density is ``sigma`` everywhere (colour ``sigmoid(logit)`` grey).

    Tables of ones make every encoded feature 1; the first layer sums them to 1 per hidden unit,
    the second maps the hidden units to ``log(sigma)``.
    """
    params = init_params(cfg, 1, generator=torch.Generator().manual_seed(0))
    params["tables"] = torch.ones_like(params["tables"])
    params["density0"] = torch.full_like(params["density0"], 1.0 / cfg.encoding.output_dim)
    params["density1"] = torch.zeros_like(params["density1"])
    params["density1"][..., 0] = math.log(sigma) / cfg.hidden
    params["color0"] = torch.zeros_like(params["color0"])
    params["color1"] = torch.zeros_like(params["color1"])
    params["color2"] = torch.zeros_like(params["color2"])
    if logit:
        params["color0"][..., 0, :] = 1.0  # SH band 0 is a constant: a view-independent bias
        params["color1"] = torch.eye(cfg.color_hidden)[None].clone()
        params["color2"] = torch.full_like(params["color2"], logit / cfg.color_hidden / 0.28209479177387814)
    return params


def camera(distance: float = 2.0, width: int = 16, fov: float = 2 * math.atan(0.5)):
    """An identity-rotation camera on +Z looking at the origin: pose, intrinsics and its rays."""
    c2w = torch.eye(4)
    c2w[2, 3] = distance
    intrinsics = Intrinsics.centred(width, width, focal_from_fov(width, fov))
    origins, directions = pixel_rays(c2w, intrinsics)
    return c2w, intrinsics, origins.reshape(-1, 3), directions.reshape(-1, 3)
