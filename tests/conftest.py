"""Shared fixtures: tiny fields with known densities, a tiny synthetic object to fit, and a tiny
procedural category with a prior trained on it (built once per test run)."""

from __future__ import annotations

import math
from pathlib import Path

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


def tiny_train(steps: int, **kw):
    """A training config small enough for tests (seconds on 2 cores)."""
    from model.train.prior import TrainConfig

    return TrainConfig(
        steps=steps, objects_per_step=4, rays_per_step=1024, lr=1e-2, grid_resolution=24, validate_every=20,
        validation_instances=2, checkpoint_every=kw.pop("checkpoint_every", 1000), log_every=10, **kw,
    )


@pytest.fixture(scope="session")
def chairs(tmp_path_factory) -> Path:
    """Six procedural chairs with two colour variants each: 24 views of 32x32 per object."""
    from model.cli.main import main

    root = tmp_path_factory.mktemp("category")
    assert main(["data", "synth", "--out", str(root), "--objects", "6", "--views", "24", "--res", "32", "--seed", "5", "--variants", "2"]) == 0
    return root


@pytest.fixture(scope="session")
def trained(chairs, tmp_path_factory) -> tuple[Path, dict]:
    """A tiny prior trained for 150 steps on ``chairs``: (run folder, training summary)."""
    from model.prior.hypernet import preset
    from model.train.prior import train

    run = tmp_path_factory.mktemp("prior")
    summary = train(chairs, run, preset("tiny"), tiny_train(150), progress=False)
    return run, summary
