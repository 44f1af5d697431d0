"""The positional-encoding NeRF field (ablation without MRHE): shapes, encoding, numerics, rendering."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import camera
from model.nerf.fields.hashgrid import FieldConfig
from model.nerf.mesh import field_mesh
from model.nerf import config
from model.nerf.fields import field_config_from_dict
from model.nerf.occupancy import OccupancyGrid
from model.nerf.fields.positional import PEFieldConfig, positional_encoding
from model.nerf.scene import UNIT_BOX
from model.nerf.renderer import RenderConfig, render_rays

TRAIN = RenderConfig(termination_threshold=0.0, color_weight_threshold=0.0, samples_per_ray=16)


@pytest.fixture
def tiny_pe_cfg() -> PEFieldConfig:
    return PEFieldConfig(position_frequencies=3, direction_frequencies=2, depth=4, width=16, skip=1)


def _params(cfg, batch=1, seed=0):
    return cfg.init_params(batch, generator=torch.Generator().manual_seed(seed))


def _face_points(n_per_axis: int = 3) -> torch.Tensor:
    """Points on all six faces, edges and corners of the unit box, plus the centre."""
    ticks = torch.linspace(0.0, 1.0, n_per_axis)
    grid = torch.cartesian_prod(ticks, ticks, ticks)
    on_face = ((grid == 0) | (grid == 1)).any(dim=-1)
    return torch.cat([grid[on_face], torch.full((1, 3), 0.5)])


def test_defaults_follow_nerf():
    cfg = PEFieldConfig()
    assert (cfg.position_frequencies, cfg.direction_frequencies, cfg.depth, cfg.skip) == (10, 4, 8, 4)
    assert cfg.color_hidden == cfg.width // 2
    assert (cfg.position_dim, cfg.direction_dim) == (63, 27)
    shapes = cfg.param_shapes()
    assert shapes["trunk0"] == (63, cfg.width)
    assert shapes["trunk5"] == (cfg.width + 63, cfg.width)  # NeRF's skips=[4]: layer 4's activation + input
    assert all(shapes[f"trunk{i}"] == (cfg.width, cfg.width) for i in (1, 2, 3, 4, 6, 7))
    assert shapes["density"] == (cfg.width, 1) and shapes["feature"] == (cfg.width, cfg.width)
    assert shapes["color0"] == (cfg.width + 27, cfg.color_hidden) and shapes["color1"] == (cfg.color_hidden, 3)


def test_param_count_matches_the_hash_grid_field():
    pe, hashgrid = PEFieldConfig().param_count(), FieldConfig().param_count()
    assert hashgrid == 74_880
    assert abs(pe - hashgrid) / hashgrid < 0.10
    # the default width is the closest one: a unit narrower or wider is further away
    for width in (PEFieldConfig().width - 1, PEFieldConfig().width + 1):
        assert abs(PEFieldConfig(width=width).param_count() - hashgrid) > abs(pe - hashgrid)


def test_shapes_and_param_shapes_agree(tiny_pe_cfg):
    params = _params(tiny_pe_cfg, batch=2)
    shapes = tiny_pe_cfg.param_shapes()
    assert list(params) == list(shapes)
    assert all(tuple(params[k].shape) == (2, *shapes[k]) for k in shapes)
    assert sum(p[0].numel() for p in params.values()) == tiny_pe_cfg.param_count()
    assert set(tiny_pe_cfg.shape_param_names()) | set(tiny_pe_cfg.color_param_names()) == set(shapes)
    assert not set(tiny_pe_cfg.shape_param_names()) & set(tiny_pe_cfg.color_param_names())

    points, dirs = torch.rand(2, 5, 3), torch.nn.functional.normalize(torch.randn(2, 7, 3), dim=-1)
    sigma, geo = tiny_pe_cfg.density(params, points)
    assert sigma.shape == (2, 5) and geo.shape == (2, 5, tiny_pe_cfg.width)
    view = tiny_pe_cfg.view_term(params, dirs)
    assert view.shape == (2, 7, tiny_pe_cfg.color_hidden)
    rgb = tiny_pe_cfg.color_from_view_term(params, geo, view[:, :5])
    assert rgb.shape == (2, 5, 3) and ((rgb >= 0) & (rgb <= 1)).all()
    # objects are independent: object 1 alone gives the same density
    sigma1, _ = tiny_pe_cfg.density({k: v[1:] for k, v in params.items()}, points[1:])
    assert torch.allclose(sigma1[0], sigma[1])


def test_dict_round_trip(tiny_pe_cfg):
    for cfg in (tiny_pe_cfg, PEFieldConfig(), PEFieldConfig(skip=None, color_hidden=7)):
        data = config.to_dict(cfg)
        assert data["kind"] == "positional"
        assert config.from_dict(PEFieldConfig, data) == cfg
        rebuilt = field_config_from_dict(data)
        assert isinstance(rebuilt, PEFieldConfig) and rebuilt == cfg


def test_invalid_configs_are_rejected():
    with pytest.raises(ValueError, match="skip"):
        PEFieldConfig(depth=4, skip=3)
    with pytest.raises(ValueError, match="positive"):
        PEFieldConfig(width=0)


def test_positional_encoding_of_a_known_value():
    x = torch.tensor([[0.25, -0.5, 0.0]])
    enc = positional_encoding(x, 2)
    assert enc.shape == (1, 3 * 5)
    expected = [0.25, -0.5, 0.0]
    for k in range(2):
        angle = [2**k * math.pi * v for v in (0.25, -0.5, 0.0)]
        expected += [math.sin(a) for a in angle] + [math.cos(a) for a in angle]
    assert torch.allclose(enc[0], torch.tensor(expected), atol=1e-6)
    assert torch.equal(positional_encoding(x, 0), x)


def test_points_are_mapped_to_minus_one_one(tiny_pe_cfg):
    """Point 0 and 1 encode as -1 and +1: the identity part of trunk0 sees [-1, 1]."""
    params = _params(tiny_pe_cfg)
    enc = tiny_pe_cfg._encode_points(params, torch.tensor([[[0.0, 1.0, 0.5]]]))
    assert torch.allclose(enc[0, 0, :3], torch.tensor([-1.0, 1.0, 0.0]))


def test_density_finite_and_non_negative_on_box_faces():
    cfg = PEFieldConfig()
    params = _params(cfg)
    pts = _face_points()[None]
    sigma, geo = cfg.density(params, pts)
    assert torch.isfinite(sigma).all() and (sigma >= 0).all() and torch.isfinite(geo).all()
    # initial density is moderate: neither empty nor opaque
    sigma_inside, _ = cfg.density(params, torch.rand(1, 512, 3, generator=torch.Generator().manual_seed(1)))
    median = sigma_inside.median().item()
    assert 0.05 < median < 20.0


def test_gradients_reach_every_parameter(tiny_pe_cfg):
    params = {k: v.clone().requires_grad_() for k, v in _params(tiny_pe_cfg).items()}
    pts = torch.cat([_face_points(), torch.rand(32, 3)])[None]
    dirs = torch.nn.functional.normalize(torch.randn(1, pts.shape[1], 3), dim=-1)
    sigma, geo = tiny_pe_cfg.density(params, pts)
    rgb = tiny_pe_cfg.color_from_view_term(params, geo, tiny_pe_cfg.view_term(params, dirs))
    (sigma.sum() + rgb.sum()).backward()
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_view_term_split_equals_the_concatenated_colour_net(tiny_pe_cfg):
    params = _params(tiny_pe_cfg, batch=2)
    points = torch.rand(2, 6, 3)
    dirs = torch.nn.functional.normalize(torch.randn(2, 6, 3), dim=-1)
    _, geo = tiny_pe_cfg.density(params, points)
    split = tiny_pe_cfg.color_from_view_term(params, geo, tiny_pe_cfg.view_term(params, dirs))
    concat = torch.cat([geo, positional_encoding(dirs, tiny_pe_cfg.direction_frequencies)], dim=-1)
    direct = torch.sigmoid(torch.relu(concat @ params["color0"]) @ params["color1"])
    assert torch.allclose(split, direct, atol=1e-6)
    assert torch.allclose(tiny_pe_cfg.color(params, geo, dirs), direct, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_low_precision_autocast(tiny_pe_cfg, dtype):
    params = {k: v.clone().requires_grad_() for k, v in _params(tiny_pe_cfg).items()}
    pts = torch.cat([_face_points(), torch.rand(16, 3)])[None]
    dirs = torch.nn.functional.normalize(torch.randn(1, pts.shape[1], 3), dim=-1)
    with torch.no_grad():
        ref_sigma, ref_geo = tiny_pe_cfg.density(params, pts)
        ref_rgb = tiny_pe_cfg.color(params, ref_geo, dirs)
    with torch.autocast("cpu", dtype=dtype):
        sigma, geo = tiny_pe_cfg.density(params, pts)
        rgb = tiny_pe_cfg.color_from_view_term(params, geo, tiny_pe_cfg.view_term(params, dirs))
    assert sigma.dtype == torch.float32
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()
    assert torch.allclose(sigma, ref_sigma, rtol=0.1, atol=1e-2)
    assert (rgb.float() - ref_rgb).abs().max() < 0.02
    (sigma.sum() + rgb.float().sum()).backward()
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_large_log_density_stays_finite_under_float16_autocast(tiny_pe_cfg):
    """exp(15) overflows float16; the density is exponentiated in float32."""
    params = _params(tiny_pe_cfg)
    params["density"] = torch.full_like(params["density"], 50.0)
    with torch.autocast("cpu", dtype=torch.float16):
        sigma, _ = tiny_pe_cfg.density(params, torch.rand(1, 8, 3))
    assert torch.isfinite(sigma).all()


def test_render_rays_with_the_pe_field(tiny_pe_cfg):
    params = {k: v.clone().requires_grad_() for k, v in _params(tiny_pe_cfg).items()}
    _, _, o, d = camera(width=4)
    out = render_rays(params, tiny_pe_cfg, o, d, TRAIN, scene=UNIT_BOX)
    assert out["rgb"].shape == (16, 3) and out["samples"] > 0
    for key in ("rgb", "opacity", "depth"):
        assert torch.isfinite(out[key]).all(), key
    assert ((out["opacity"] >= 0) & (out["opacity"] <= 1 + 1e-6)).all()
    (out["rgb"].sum() + out["opacity"].sum()).backward()
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_mesh_of_a_pe_field_inside_its_grid(tiny_pe_cfg):
    """Meshes come from any field kind (the no-MRHE ablation has no hash tables)."""
    params = _params(tiny_pe_cfg)
    params["density"] = params["density"].abs() * 200  # dense wherever the trunk is active
    occupied = torch.zeros(16, 16, 16, dtype=torch.bool)
    occupied[4:12, 4:12, 4:12] = True
    grid = OccupancyGrid(occupied, torch.full((3,), -0.5), torch.full((3,), 0.5))
    mesh = field_mesh(params, tiny_pe_cfg, grid, UNIT_BOX, resolution=24)
    assert len(mesh.faces) > 0 and np.isfinite(mesh.vertices).all()
    # the density outside the grid counts as zero, so the surface stays in the occupied cube
    cell = 1 / 16
    assert (mesh.vertices >= -0.25 - cell).all() and (mesh.vertices <= 0.25 + cell).all()
