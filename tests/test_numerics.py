"""Numerical hard cases: each must give finite values and finite gradients, or a clear error."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import camera, constant_field
from model.data.dataset import DatasetError, validate_views
from model.nerf.encodings.hashgrid import encode
from model.nerf.fields.hashgrid import density, init_params
from model.nerf.occupancy import OccupancyGrid
from model.nerf.rays import Intrinsics
from model.nerf.scene import UNIT_BOX, SceneBox
from model.nerf.renderer import DENSE, RenderConfig, composite_weights, render_image, render_rays

TRAIN = RenderConfig(termination_threshold=0.0)


def _render_with_grad(params, cfg, o, d, render_cfg=TRAIN, **kw):
    params = {k: v.clone().requires_grad_() for k, v in params.items()}
    out = render_rays(params, cfg, o, d, render_cfg, **kw, scene=UNIT_BOX)
    (out["rgb"].sum() + out["opacity"].sum()).backward()
    return out, params


def _all_finite(out, params):
    for key in ("rgb", "opacity", "depth"):
        assert torch.isfinite(out[key]).all(), key
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("sigma", [1e3, 1e6])
def test_extreme_density_stays_finite(tiny_field_cfg, sigma):
    params = constant_field(tiny_field_cfg, sigma=sigma)
    _, _, o, d = camera(width=8)
    out, grads = _render_with_grad(params, tiny_field_cfg, o, d)
    _all_finite(out, grads)
    hit = out["samples"] > 0
    assert hit and torch.allclose(out["opacity"].max(), torch.tensor(1.0))
    assert (out["opacity"] <= 1 + 1e-6).all()


def test_composite_weights_at_huge_optical_depth():
    sd = torch.tensor([[1e6, 1e6, 1e6], [0.0, 1e9, 0.0], [3e38, 0.0, 0.0]])
    w = composite_weights(sd)
    assert torch.isfinite(w).all()
    assert torch.allclose(w.sum(1), torch.ones(3))


def test_rays_that_miss_the_box(tiny_field_cfg):
    params = constant_field(tiny_field_cfg, sigma=10.0)
    o = torch.tensor([[3.0, 3.0, 3.0], [0.0, 0.0, 2.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # away from the box / pointing back out
    out = render_rays(params, tiny_field_cfg, o, d, TRAIN, scene=UNIT_BOX)
    assert out["samples"] == 0
    # nothing was evaluated, so the loss of these rays has no gradient path (callers skip the step)
    assert not out["rgb"].requires_grad
    assert torch.equal(out["opacity"], torch.zeros(2)) and torch.equal(out["rgb"], torch.ones(2, 3))


def test_camera_inside_the_box(tiny_field_cfg):
    params = constant_field(tiny_field_cfg, sigma=2.0)
    c2w, intrinsics, _, _ = camera(distance=0.1, width=8)
    out = render_image(params, tiny_field_cfg, c2w, intrinsics, DENSE, scene=UNIT_BOX)
    assert torch.isfinite(out["rgb"]).all() and out["samples"] > 0
    # centre ray: from z=0.1 down to z=-0.5, a chord of 0.6
    assert abs(float(out["opacity"][4, 4]) - (1 - torch.exp(torch.tensor(-1.2)).item())) < 0.02


def test_grazing_and_axis_parallel_rays(tiny_field_cfg):
    params = constant_field(tiny_field_cfg, sigma=5.0)
    o = torch.tensor([[-2.0, 0.5, 0.0], [-2.0, 0.5, 0.5], [0.5, 0.5, 2.0], [-2.0, 0.0, 0.0], [-2.0, 0.5 + 1e-7, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 1e-12, -1e-12], [1.0, 0.0, 0.0]])
    d = d / d.norm(dim=-1, keepdim=True)
    out, grads = _render_with_grad(params, tiny_field_cfg, o, d)
    _all_finite(out, grads)
    assert out["opacity"][3].item() > 0.99  # straight through the middle: depth 5


def test_points_on_box_faces_corners_and_cell_borders(tiny_field_cfg):
    params = constant_field(tiny_field_cfg, sigma=3.0)
    res = tiny_field_cfg.encoding.base_resolution
    border = torch.arange(res + 1, dtype=torch.float32) / res  # cell borders of the coarsest level
    pts = torch.cartesian_prod(border, torch.tensor([0.0, 1.0]), torch.tensor([0.0, 0.5, 1.0]))
    sigma, geo = density(params, pts[None], tiny_field_cfg)
    assert torch.allclose(sigma, torch.full_like(sigma, 3.0), rtol=1e-5)
    feats = encode(pts[None].requires_grad_(), params["tables"], tiny_field_cfg.encoding)
    assert torch.isfinite(feats).all()
    grid = OccupancyGrid(torch.ones(4, 4, 4, dtype=torch.bool), torch.full((3,), -0.5), torch.full((3,), 0.5))
    corners = torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [0.25, -0.25, 0.5]])
    assert grid.lookup(corners).all()
    assert not grid.lookup(torch.tensor([[0.5001, 0.0, 0.0]])).any()


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_low_precision_autocast(tiny_field_cfg, dtype):
    params = constant_field(tiny_field_cfg, sigma=1e4, logit=1.0)
    _, _, o, d = camera(width=8)
    reference = render_rays(params, tiny_field_cfg, o, d, TRAIN, scene=UNIT_BOX)
    with torch.autocast("cpu", dtype=dtype):
        out, grads = _render_with_grad(params, tiny_field_cfg, o, d)
    _all_finite(out, grads)
    assert out["rgb"].dtype == torch.float32
    assert (out["rgb"] - reference["rgb"]).abs().max() < 0.02


def test_density_of_large_log_density_stays_finite_under_float16_autocast(tiny_field_cfg):
    """exp(x) overflows float16 above x = 11.1; densities of 1e6 (log 13.8) must survive autocast."""
    params = constant_field(tiny_field_cfg, sigma=1e6)
    with torch.autocast("cpu", dtype=torch.float16):
        sigma, _ = density(params, torch.rand(1, 16, 3), tiny_field_cfg)
    assert sigma.dtype == torch.float32 and torch.isfinite(sigma).all()
    assert torch.allclose(sigma, torch.full_like(sigma, 1e6), rtol=2e-2)


def test_all_white_and_all_black_targets_train_to_finite_values(tiny_field_cfg):
    params = {k: v.clone().requires_grad_() for k, v in constant_field(tiny_field_cfg, sigma=1.0).items()}
    _, _, o, d = camera(width=8)
    opt = torch.optim.Adam(params.values(), lr=1e-2)
    for target in (torch.ones(64, 3), torch.zeros(64, 3)):
        for _ in range(3):
            out = render_rays(params, tiny_field_cfg, o, d, TRAIN, background=torch.rand(64, 3), scene=UNIT_BOX)
            loss = ((out["rgb"] - target) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            assert torch.isfinite(loss)
            assert all(torch.isfinite(p).all() for p in params.values())


def test_nan_and_inf_in_poses_and_images_are_rejected(tiny_field_cfg):
    images = torch.rand(2, 4, 4, 4)
    poses = torch.eye(4).repeat(2, 1, 1)
    validate_views(images, poses)
    bad_pose = poses.clone()
    bad_pose[1, 0, 3] = float("nan")
    with pytest.raises(DatasetError, match="NaN or Inf"):
        validate_views(images, bad_pose)
    bad_image = images.clone()
    bad_image[0, 1, 1, 0] = float("inf")
    with pytest.raises(DatasetError, match="NaN or Inf"):
        validate_views(bad_image, poses)
    params = constant_field(tiny_field_cfg, sigma=1.0)
    with pytest.raises(ValueError, match="NaN/Inf"):
        render_image(params, tiny_field_cfg, bad_pose[1], Intrinsics.centred(4, 4, 4.0), DENSE, scene=UNIT_BOX)
    with pytest.raises(ValueError, match="focal"):
        Intrinsics.centred(4, 4, float("inf"))


def test_transmittance_keeps_its_precision_after_a_huge_optical_depth():
    # one sample of depth 1e8 in front of tiny ones: cumsum - x would cancel them to 0 or noise
    depth = torch.tensor([[1e-7, 1e-7, 1e8, 1e-7]])
    weights = composite_weights(depth)
    assert torch.isfinite(weights).all()
    assert weights[0, 1] == pytest.approx((1 - math.exp(-1e-7)) * math.exp(-1e-7), rel=1e-4)
    assert weights[0, 2] == pytest.approx(math.exp(-2e-7), rel=1e-5) and weights[0, 3] == 0.0


def test_a_sample_whose_colour_is_skipped_goes_to_the_background(tiny_field_cfg):
    # a faint field: every sample's weight is below the colour threshold, so none is shaded
    params = constant_field(tiny_field_cfg, 1e-3, logit=-8.0)  # near-black colour if shaded
    _, _, o, d = camera(width=4)
    cfg = RenderConfig(color_weight_threshold=1e-2, termination_threshold=0.0)
    out = render_rays(params, tiny_field_cfg, o, d, cfg, scene=UNIT_BOX, background=torch.tensor([0.2, 0.9, 0.4]))
    assert torch.allclose(out["rgb"], torch.tensor([0.2, 0.9, 0.4]).expand_as(out["rgb"]))  # not darkened
    assert float(out["opacity"].max()) == 0.0


def test_rendering_is_invariant_to_the_scene_scale(tiny_field_cfg):
    params = init_params(tiny_field_cfg, 1, generator=torch.Generator().manual_seed(2))
    c2w, intrinsics, _, _ = camera(distance=2.0, width=6)
    small = render_image(params, tiny_field_cfg, c2w, intrinsics, DENSE, scene=UNIT_BOX)
    big_pose = c2w.clone()
    big_pose[:3, 3] *= 3.0
    big = render_image(params, tiny_field_cfg, big_pose, intrinsics, DENSE, scene=SceneBox.cube(1.5))
    assert torch.allclose(small["rgb"], big["rgb"], atol=1e-5) and torch.allclose(3 * small["depth"], big["depth"], rtol=1e-4, atol=1e-5)


def test_a_camera_inside_a_large_box_renders_finite_images(tiny_field_cfg):
    params = constant_field(tiny_field_cfg, 50.0)
    c2w, intrinsics, _, _ = camera(distance=0.2, width=4)
    out = render_image(params, tiny_field_cfg, c2w, intrinsics, DENSE, scene=SceneBox.cube(10.0))
    assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["depth"]).all()
