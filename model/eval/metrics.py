"""Evaluation metrics: PSNR (full image and foreground, beside the blank-image floor), SSIM and
Chamfer distance.

* PSNR is a one-line formula on the mean squared error, computed here in torch on the inputs'
  device.
* SSIM comes from ``pytorch-msssim`` (a small, well-tested torch implementation that runs on the
  inputs' device) with the constants of Wang et al. 2004: an 11-tap Gaussian window of sigma 1.5,
  K1 = 0.01, K2 = 0.03, data range 1, valid (unpadded) filtering, computed per RGB channel and
  averaged.
* Chamfer distance uses ``scipy.spatial.cKDTree`` for nearest neighbours and ``trimesh`` to sample
  points on mesh surfaces.

Images are float arrays or tensors in [0, 1] with a trailing RGB axis, ``[H, W, 3]`` or batched
``[..., H, W, 3]``; composite RGBA onto a background before measuring.
"""

from __future__ import annotations

import math

import numpy as np
import pytorch_msssim
import torch
import trimesh
from scipy.spatial import cKDTree

from model.nerf.mesh import sample_surface

# PSNR of identical images is +inf; it is capped here so that means over views and tables stay
# finite. 100 dB is an MSE of 1e-10, far below the float32 rendering noise of any real image.
PSNR_CAP_DB = 100.0

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K = (0.01, 0.03)

# Accept values a hair outside [0, 1] (float round-off in renders); anything further is a caller
# mistake, most often 0..255 images.
_RANGE_SLACK = 1e-3


def _as_tensor(x) -> torch.Tensor:
    return (x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))).detach()


def _check_images(pred, target) -> tuple[torch.Tensor, torch.Tensor]:
    pred = _as_tensor(pred).float()
    target = _as_tensor(target).to(device=pred.device, dtype=torch.float32)
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    if pred.ndim < 3 or pred.shape[-1] != 3:
        raise ValueError(f"images must be [..., H, W, 3] (RGB last), got {tuple(pred.shape)}")
    if pred.numel() == 0:
        raise ValueError(f"images are empty: {tuple(pred.shape)}")
    for name, img in (("pred", pred), ("target", target)):
        if not torch.isfinite(img).all():
            raise ValueError(f"{name} contains NaN or infinite values")
        lo, hi = img.min().item(), img.max().item()
        if lo < -_RANGE_SLACK or hi > 1.0 + _RANGE_SLACK:
            raise ValueError(f"{name} values must lie in [0, 1], got [{lo:.4g}, {hi:.4g}]")
    return pred.clamp(0.0, 1.0), target.clamp(0.0, 1.0)


def psnr(pred, target, mask=None) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (peak 1).

    ``pred``/``target``: ``[H, W, 3]`` or ``[..., H, W, 3]``. For a batch the result is the mean
    of per-image PSNRs (the convention of NeRF papers), not the PSNR of the pooled MSE.
    ``mask`` (optional, boolean ``[..., H, W]`` or ``[..., H, W, 1]``, broadcast over the batch)
    restricts each image's MSE to the selected pixels; every image needs at least one.
    Each per-image PSNR is capped at ``PSNR_CAP_DB`` (100 dB), so identical images give 100.
    """
    pred, target = _check_images(pred, target)
    sq_err = (pred - target).square().mean(dim=-1)  # [..., H, W]
    if mask is None:
        mse = sq_err.flatten(-2).mean(dim=-1)
    else:
        m = _as_tensor(mask).to(pred.device)
        if m.ndim == sq_err.ndim + 1 and m.shape[-1] == 1:
            m = m[..., 0]
        if m.dtype != torch.bool:
            raise ValueError(f"mask must be boolean, got {m.dtype}")
        try:
            m = torch.broadcast_to(m, sq_err.shape)
        except RuntimeError as e:
            raise ValueError(f"mask shape {tuple(m.shape)} does not match images {tuple(pred.shape)}") from e
        count = m.flatten(-2).sum(dim=-1)
        if (count == 0).any():
            raise ValueError("mask selects no pixel in at least one image")
        mse = (sq_err * m).flatten(-2).sum(dim=-1) / count
    per_image = -10.0 * torch.log10(mse.clamp_min(10.0 ** (-PSNR_CAP_DB / 10.0)))
    return float(per_image.mean())


# A predicted pixel is foreground when its opacity would survive 8-bit quantisation (the alpha an
# RGBA PNG of the render would store is non-zero).
PREDICTED_ALPHA_MIN = 1.0 / 255.0
FOREGROUND_DEFINITION = "pixels where the ground-truth alpha > 0 or the rendered opacity >= 1/255"


def foreground_mask(target_alpha, pred_opacity=None) -> torch.Tensor:
    """Boolean ``[..., H, W]``: where the ground truth (``target_alpha``) or the render has alpha."""
    mask = _as_tensor(target_alpha) > 0
    if pred_opacity is not None:
        mask = mask | (_as_tensor(pred_opacity).to(mask.device) >= PREDICTED_ALPHA_MIN)
    return mask


def image_quality(pred, target_rgba, pred_opacity=None, background=(1.0, 1.0, 1.0)) -> dict:
    """PSNR of renders against RGBA ground truth, over the full image and over the foreground, with
    the floor: the same two figures for a blank image of the background colour.

    ``pred [V, H, W, 3]``, ``target_rgba [V, H, W, 4]`` (straight alpha, composited here over
    ``background``), ``pred_opacity [V, H, W]`` (optional). The floor is scored on the same pixels
    as the render, so a blank render scores exactly the floor; a quality figure only means
    something above it. Views with no foreground pixel are left out of the foreground means.
    """
    pred = _as_tensor(pred).float()
    target_rgba = _as_tensor(target_rgba).to(device=pred.device, dtype=torch.float32)
    bg = torch.tensor(background, dtype=torch.float32, device=pred.device)
    target = target_rgba[..., :3] * target_rgba[..., 3:] + bg * (1 - target_rgba[..., 3:])
    blank = bg.expand_as(target)
    mask = foreground_mask(target_rgba[..., 3], pred_opacity)
    views = [v for v in range(pred.shape[0]) if bool(mask[v].any())]
    per_view = [psnr(pred[v], target[v]) for v in range(pred.shape[0])]
    per_view_fg = [psnr(pred[v], target[v], mask[v]) for v in views]
    return {
        "psnr": sum(per_view) / len(per_view),
        "psnr_fg": sum(per_view_fg) / len(per_view_fg) if views else None,
        "floor_psnr": psnr(blank, target),
        "floor_psnr_fg": sum(psnr(blank[v], target[v], mask[v]) for v in views) / len(views) if views else None,
        "foreground_fraction": float(mask.float().mean()),
        "psnr_per_view": per_view,
        "foreground": FOREGROUND_DEFINITION,
    }


def ssim(pred, target) -> float:
    """Structural similarity of images in [0, 1], ``[H, W, 3]`` or ``[V, H, W, 3]`` (mean over V).

    Gaussian window of ``SSIM_WINDOW`` taps, sigma ``SSIM_SIGMA``, constants ``SSIM_K``, valid
    filtering (no padding), per RGB channel then averaged. Images smaller than the window (side
    below 11 pixels) get the largest odd window that fits, with the same sigma; a 24x24 image
    uses the full window. Sides below 3 pixels raise ValueError (no local statistics exist).
    """
    pred, target = _check_images(pred, target)
    if pred.ndim == 3:
        pred, target = pred[None], target[None]
    if pred.ndim != 4:
        raise ValueError(f"ssim takes [H, W, 3] or [V, H, W, 3], got {tuple(pred.shape)}")
    side = min(pred.shape[1], pred.shape[2])
    if side < 3:
        raise ValueError(f"ssim needs images of at least 3x3 pixels, got {pred.shape[1]}x{pred.shape[2]}")
    win = min(SSIM_WINDOW, side if side % 2 == 1 else side - 1)
    x = pred.permute(0, 3, 1, 2).contiguous()
    y = target.permute(0, 3, 1, 2).contiguous()
    value = pytorch_msssim.ssim(x, y, data_range=1.0, size_average=True, win_size=win,
                                win_sigma=SSIM_SIGMA, K=SSIM_K)
    return float(value)


def _check_points(points, name: str) -> np.ndarray:
    if isinstance(points, torch.Tensor):
        points = points.detach().cpu().numpy()
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must be [N, 3] points, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name} contains NaN or infinite coordinates")
    return p


def chamfer_distance(points_a, points_b) -> float:
    """Symmetric Chamfer distance between point sets ``[N, 3]`` and ``[M, 3]``.

    ``0.5 * (mean_a min_b |a - b| + mean_b min_a |b - a|)``: plain (not squared) Euclidean
    nearest-neighbour distances, each direction averaged over its points, then the two directions
    averaged. The result is in the points' own units (scene-box units for this project's meshes;
    see ``mesh_chamfer``). If either set is empty the distance is ``inf`` (nothing to match), so
    an evaluation reports a failed reconstruction instead of crashing.
    """
    a = _check_points(points_a, "points_a")
    b = _check_points(points_b, "points_b")
    if len(a) == 0 or len(b) == 0:
        return math.inf
    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def mesh_chamfer(mesh_a: trimesh.Trimesh, mesh_b: trimesh.Trimesh, n_points: int = 4096,
                 seed: int = 0, unit: float = 1.0) -> float:
    """Chamfer distance between two surfaces, as in the paper: 4096 points per surface.

    Each mesh is sampled with its own generator seeded by ``seed`` (area-weighted, uniform), so
    the value is deterministic, symmetric in its arguments, and exactly 0 for identical meshes.
    Distances are ``chamfer_distance`` (mean, unsquared, halved sum of both directions) divided by
    ``unit`` (pass the scene box's longest side): scene-box units at any world scale. This
    project's meshes live in [-0.5, 0.5]^3 with objects normalised to a longest side of 0.9, so
    0.01 is 1.1% of the object's longest side. An empty (or zero-area) mesh on either side gives ``inf``.
    """
    return chamfer_distance(sample_surface(mesh_a, n_points, seed), sample_surface(mesh_b, n_points, seed)) / unit
