import math

import numpy as np
import pytest
import torch
import trimesh
from skimage.metrics import structural_similarity

from model.eval.metrics import PSNR_CAP_DB, chamfer_distance, mesh_chamfer, psnr, sample_surface, ssim


def _image(h=24, w=24, seed=0):
    return torch.rand(h, w, 3, generator=torch.Generator().manual_seed(seed))


# ---- PSNR ----

def test_psnr_uniform_error():
    target = torch.full((8, 8, 3), 0.5)
    assert psnr(target + 0.1, target) == pytest.approx(20.0, abs=1e-4)
    assert psnr(target + 0.01, target) == pytest.approx(40.0, abs=1e-3)


def test_psnr_batch_is_mean_of_per_image():
    target = torch.full((2, 8, 8, 3), 0.5)
    pred = target.clone()
    pred[0] += 0.1
    pred[1] += 0.01
    assert psnr(pred, target) == pytest.approx(30.0, abs=1e-3)


def test_psnr_identical_is_capped():
    img = _image()
    assert psnr(img, img) == PSNR_CAP_DB
    assert math.isfinite(psnr(img[None].repeat(3, 1, 1, 1), img[None].repeat(3, 1, 1, 1)))


def test_psnr_mask_restricts_pixels():
    target = torch.full((8, 8, 3), 0.5)
    pred = target.clone()
    pred[:4] += 0.1
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[:4] = True
    assert psnr(pred, target, mask) == pytest.approx(20.0, abs=1e-4)
    assert psnr(pred, target, ~mask[..., None]) == PSNR_CAP_DB


def test_psnr_accepts_numpy():
    target = np.full((4, 4, 3), 0.5, dtype=np.float32)
    assert psnr(target + 0.1, target) == pytest.approx(20.0, abs=1e-4)


@pytest.mark.parametrize(
    "pred, target, mask, message",
    [
        (torch.zeros(4, 4, 3), torch.zeros(4, 5, 3), None, "shapes differ"),
        (torch.zeros(4, 4, 4), torch.zeros(4, 4, 4), None, "RGB"),
        (torch.full((4, 4, 3), float("nan")), torch.zeros(4, 4, 3), None, "NaN"),
        (torch.full((4, 4, 3), 255.0), torch.zeros(4, 4, 3), None, r"\[0, 1\]"),
        (torch.zeros(4, 4, 3), torch.zeros(4, 4, 3), torch.zeros(4, 4, dtype=torch.bool), "no pixel"),
        (torch.zeros(4, 4, 3), torch.zeros(4, 4, 3), torch.ones(3, 3, dtype=torch.bool), "mask shape"),
    ],
)
def test_psnr_rejects_bad_input(pred, target, mask, message):
    with pytest.raises(ValueError, match=message):
        psnr(pred, target, mask)


# ---- SSIM ----

def test_ssim_identical_is_one():
    img = _image()
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-6)


def test_ssim_decreases_with_noise():
    img = _image(32, 32)
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(img.shape, generator=g)
    low = ssim((img + 0.02 * noise).clamp(0, 1), img)
    high = ssim((img + 0.2 * noise).clamp(0, 1), img)
    assert 1.0 > low > high


def test_ssim_matches_scikit_image_gaussian_ssim():
    # The reference definition (Wang et al. 2004) as scikit-image implements it.
    img = _image(24, 24)
    noisy = (img + 0.1 * torch.randn(img.shape, generator=torch.Generator().manual_seed(2))).clamp(0, 1)
    expected = structural_similarity(noisy.numpy(), img.numpy(), channel_axis=-1, data_range=1.0,
                                     gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert ssim(noisy, img) == pytest.approx(expected, abs=1e-4)


def test_ssim_batch_is_mean_of_views():
    a = torch.stack([_image(seed=s) for s in range(3)])
    b = torch.stack([_image(seed=s + 10) for s in range(3)])
    assert ssim(a, b) == pytest.approx(np.mean([ssim(x, y) for x, y in zip(a, b)]), abs=1e-6)


def test_ssim_small_images_shrink_the_window():
    img = _image(5, 7)
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-6)
    assert ssim(1.0 - img, img) < 0.5
    with pytest.raises(ValueError, match="3x3"):
        ssim(_image(2, 8), _image(2, 8))


def test_ssim_rejects_bad_input():
    with pytest.raises(ValueError, match="shapes differ"):
        ssim(_image(8, 8), _image(8, 9))
    with pytest.raises(ValueError, match=r"\[V, H, W, 3\]"):
        ssim(torch.zeros(2, 2, 8, 8, 3), torch.zeros(2, 2, 8, 8, 3))


# ---- Chamfer ----

def test_chamfer_points_by_hand():
    a = np.array([[0.0, 0.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    # a->b: 1; b->a: (1 + 3) / 2 = 2; symmetric mean 1.5, unsquared.
    assert chamfer_distance(a, b) == pytest.approx(1.5)
    assert chamfer_distance(b, a) == pytest.approx(1.5)
    assert chamfer_distance(torch.tensor(b), torch.tensor(b)) == 0.0


def test_chamfer_empty_is_inf_and_bad_input_raises():
    assert chamfer_distance(np.zeros((0, 3)), np.zeros((5, 3))) == math.inf
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        chamfer_distance(np.zeros((5, 2)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="NaN"):
        chamfer_distance(np.full((5, 3), np.nan), np.zeros((5, 3)))


def test_mesh_chamfer_identical_meshes_is_zero():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    assert mesh_chamfer(sphere, sphere.copy()) == 0.0


def test_mesh_chamfer_concentric_spheres():
    # Every point of one sphere is |r1 - r2| from the other sphere; sampling adds a small bias.
    # Different tessellations so the two samples share no structure.
    inner = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    outer = trimesh.creation.icosphere(subdivisions=4, radius=0.4)
    value = mesh_chamfer(inner, outer)
    assert value == pytest.approx(0.1, rel=0.01)
    assert mesh_chamfer(outer, inner) == value


def test_mesh_chamfer_seeded():
    a = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    b = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    assert mesh_chamfer(a, b, seed=3) == mesh_chamfer(a, b, seed=3)
    assert mesh_chamfer(a, b, seed=3) != mesh_chamfer(a, b, seed=4)
    assert np.array_equal(sample_surface(a, 100, seed=5), sample_surface(a, 100, seed=5))
    assert sample_surface(a, 100).shape == (100, 3)


def test_mesh_chamfer_empty_mesh_is_inf():
    assert mesh_chamfer(trimesh.Trimesh(), trimesh.creation.box()) == math.inf
    with pytest.raises(ValueError, match="Trimesh"):
        mesh_chamfer(np.zeros((4, 3)), trimesh.creation.box())
    with pytest.raises(ValueError, match="n_points"):
        mesh_chamfer(trimesh.creation.box(), trimesh.creation.box(), n_points=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_image_metrics_on_cuda():
    target = torch.full((2, 16, 16, 3), 0.5, device="cuda")
    assert psnr(target + 0.1, target) == pytest.approx(20.0, abs=1e-3)
    assert ssim(target, target) == pytest.approx(1.0, abs=1e-6)
    assert chamfer_distance(torch.zeros(3, 3, device="cuda"), torch.ones(2, 3, device="cuda")) > 0
