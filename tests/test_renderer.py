"""Compositing, sampling, occupancy gating, early termination and chunking of the renderer."""

from __future__ import annotations

from dataclasses import replace

import torch

from conftest import camera, constant_field
from model.nerf.fields.hashgrid import init_params
from model.nerf.occupancy import OccupancyGrid
from model.nerf.scene import UNIT_BOX
from model.nerf.renderer import DENSE, RenderConfig, composite_weights, render_image, render_rays
from model.nerf.rays import Intrinsics, focal_from_fov, pixel_rays, ray_box_intersection
from model.nerf.sampler import stratified_distances


def naive_weights(sigma_delta: torch.Tensor) -> torch.Tensor:
    alpha = 1 - torch.exp(-sigma_delta)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
    return trans * alpha


def test_composite_weights_match_the_product_formula():
    sd = torch.rand(64, 32, dtype=torch.float64) * 0.3
    assert torch.allclose(composite_weights(sd), naive_weights(sd), atol=1e-12)
    assert (composite_weights(sd).sum(1) <= 1 + 1e-12).all()


def test_composite_weights_in_segments_equal_one_pass():
    sd = torch.rand(8, 40, dtype=torch.float64)
    whole = composite_weights(sd)
    first = composite_weights(sd[:, :15])
    second = composite_weights(sd[:, 15:], sd[:, :15].sum(1))
    assert torch.allclose(torch.cat([first, second], 1), whole, atol=1e-12)


def test_pixel_rays_centre_looks_at_origin():
    c2w = torch.eye(4)
    c2w[2, 3] = 2.0
    origins, directions = pixel_rays(c2w, Intrinsics.centred(3, 3, focal_from_fov(3, 1.0)))
    assert torch.allclose(directions[1, 1], torch.tensor([0.0, 0.0, -1.0]))
    assert torch.allclose(directions.norm(dim=-1), torch.ones(3, 3))
    assert torch.allclose(origins[0, 0], torch.tensor([0.0, 0.0, 2.0]))
    assert directions[0, 0, 0] < 0 and directions[0, 0, 1] > 0  # top-left pixel: left and up


def test_ray_box_intersection_distances():
    o = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 0.0], [3.0, 3.0, 3.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    near, far, hit = ray_box_intersection(o, d, torch.full((3,), -0.5), torch.full((3,), 0.5))
    assert hit.tolist() == [True, True, False]
    assert torch.allclose(near[:2], torch.tensor([1.5, 0.0])) and torch.allclose(far[:2], torch.tensor([2.5, 0.5]))


def test_stratified_distances_cover_the_interval():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([2.0, 2.0])
    t, delta = stratified_distances(near, far, 4)
    assert torch.allclose(t[0], torch.tensor([1.125, 1.375, 1.625, 1.875]))
    assert delta[1] == 0
    tj, _ = stratified_distances(near, far, 4, jitter=True, generator=torch.Generator().manual_seed(0))
    assert ((tj[0] >= 1.0) & (tj[0] <= 2.0)).all()


def test_uniform_slab_matches_beer_lambert(tiny_field_cfg):
    """A constant density along a 1-unit chord gives opacity 1 - exp(-sigma)."""
    params = constant_field(tiny_field_cfg, sigma=0.7)
    o = torch.tensor([[0.0, 0.0, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    out = render_rays(params, tiny_field_cfg, o, d, DENSE, scene=UNIT_BOX)
    assert torch.allclose(out["opacity"], torch.tensor([1 - torch.exp(torch.tensor(-0.7))]), atol=1e-5)
    # grey 0.5 over white: 0.5 * opacity + (1 - opacity)
    assert torch.allclose(out["rgb"], (1 - 0.5 * out["opacity"])[:, None].expand(1, 3), atol=1e-5)


def test_occupancy_gated_render_equals_dense_render_of_the_same_samples(tiny_field_cfg):
    params = constant_field(tiny_field_cfg, sigma=5.0)
    _, _, o, d = camera(width=12)
    occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
    occupied[2:6, 2:6, 2:6] = True  # a cube of side 0.5 at the centre
    grid = OccupancyGrid(occupied, torch.full((3,), -0.5), torch.full((3,), 0.5))
    gated = render_rays(params, tiny_field_cfg, o, d, replace(DENSE, tight_box=True, skip_empty=True), grid=grid, scene=UNIT_BOX)
    # The same field restricted to the cube: the analytic opacity along +-Z chords is 1-exp(-5 * length)
    centre = gated["opacity"].reshape(12, 12)[6, 6]
    assert abs(float(centre) - (1 - torch.exp(torch.tensor(-2.5)).item())) < 2e-3
    corner = gated["opacity"].reshape(12, 12)[0, 0]
    assert float(corner) == 0.0 and gated["samples"] < 12 * 12 * DENSE.samples_per_ray


def test_early_termination_skips_samples_behind_opaque_surfaces(tiny_field_cfg):
    params = constant_field(tiny_field_cfg, sigma=200.0)
    # parallel rays crossing the whole box along -Z: every chord has length 1
    xy = torch.stack(torch.meshgrid(torch.linspace(-0.4, 0.4, 6), torch.linspace(-0.4, 0.4, 6), indexing="ij"), -1)
    o = torch.cat([xy.reshape(-1, 2), torch.full((36, 1), 2.0)], dim=1)
    d = torch.tensor([0.0, 0.0, -1.0]).expand(36, 3)
    full = render_rays(params, tiny_field_cfg, o, d, replace(DENSE, march_segment=16), scene=UNIT_BOX)
    stopped = render_rays(params, tiny_field_cfg, o, d, replace(DENSE, termination_threshold=1e-4, march_segment=16), scene=UNIT_BOX)
    assert stopped["samples"] < full["samples"] / 3
    assert torch.allclose(stopped["rgb"], full["rgb"], atol=1e-3)


def test_render_image_chunks_agree_with_one_chunk(tiny_field_cfg):
    params = init_params(tiny_field_cfg, 1, generator=torch.Generator().manual_seed(3))
    c2w, intrinsics, _, _ = camera(width=10)
    one = render_image(params, tiny_field_cfg, c2w, intrinsics, replace(DENSE, chunk_rays=100), scene=UNIT_BOX)
    many = render_image(params, tiny_field_cfg, c2w, intrinsics, replace(DENSE, chunk_rays=7), scene=UNIT_BOX)
    assert torch.allclose(one["rgb"], many["rgb"], atol=1e-6)
    assert one["rgb"].shape == (10, 10, 3) and one["opacity"].shape == (10, 10)


def test_render_rays_is_differentiable(tiny_field_cfg):
    params = {k: v.requires_grad_() for k, v in init_params(tiny_field_cfg, 1, generator=torch.Generator().manual_seed(1)).items()}
    _, _, o, d = camera(width=6)
    out = render_rays(params, tiny_field_cfg, o, d, RenderConfig(termination_threshold=0.0), jitter=True, scene=UNIT_BOX)
    out["rgb"].sum().backward()
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name
