"""Occupancy grids: lookups, tight boxes, density thresholds and visual-hull carving."""

from __future__ import annotations

import math

import torch

from model.nerf.occupancy import OccupancyGrid, carve_from_masks, cell_centers, density_threshold, dilate, grid_from_density
from model.nerf.rays import Intrinsics, focal_from_fov, pixel_rays, ray_box_intersection
from model.nerf.scene import UNIT_BOX

LO, HI = torch.full((3,), -0.5), torch.full((3,), 0.5)


def sphere_density(radius=0.25, centre=(0.1, 0.0, -0.1)):
    c = torch.tensor(centre)
    return lambda p: 100.0 * ((p - c).norm(dim=-1) < radius).float()


def test_grid_from_density_covers_the_sphere_and_little_else():
    grid = grid_from_density(sphere_density(), UNIT_BOX, resolution=32, dilation=1)
    centers = cell_centers(32, LO, HI)
    dist = (centers - torch.tensor([0.1, 0.0, -0.1])).norm(dim=-1)
    occ = grid.occupied.reshape(-1)
    assert occ[dist < 0.22].all()
    assert not occ[dist > 0.25 + 3 * math.sqrt(3) / 32].any()
    lo, hi = grid.tight_box()
    assert torch.allclose(lo, torch.tensor([0.1, 0.0, -0.1]) - 0.25, atol=2.5 / 32)
    assert torch.allclose(hi, torch.tensor([0.1, 0.0, -0.1]) + 0.25, atol=2.5 / 32)


def test_empty_grid_has_no_tight_box():
    grid = grid_from_density(lambda p: torch.zeros(p.shape[0]), UNIT_BOX, resolution=8)
    assert grid.tight_box() is None and grid.fraction == 0.0


def test_density_threshold_is_the_cell_opacity():
    thr = density_threshold(64, 0.01)
    assert abs((1 - math.exp(-thr / 64)) - 0.01) < 1e-9


def test_dilate_grows_by_one_cell():
    occ = torch.zeros(5, 5, 5, dtype=torch.bool)
    occ[2, 2, 2] = True
    assert dilate(occ, 1).sum() == 27 and dilate(occ, 0).sum() == 1


def test_state_dict_round_trip():
    grid = grid_from_density(sphere_density(), UNIT_BOX, resolution=8)
    again = OccupancyGrid.from_state_dict(grid.state_dict())
    assert torch.equal(again.occupied, grid.occupied) and torch.equal(again.box_max, grid.box_max)


def _silhouettes(poses, width, focal, radius=0.25):
    """Exact masks of a sphere at the origin: rays that pass within ``radius`` of it."""
    origins, directions = pixel_rays(poses, Intrinsics.centred(width, width, focal))
    closest = origins - (origins * directions).sum(-1, keepdim=True) * directions
    return closest.norm(dim=-1) < radius


def _look_at(eye):
    eye = torch.tensor(eye, dtype=torch.float32)
    back = eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back)
    right = right / right.norm()
    up = torch.linalg.cross(back, right)
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, eye
    return c2w


def test_visual_hull_keeps_the_object_and_carves_the_rest():
    eyes = [(2, 0, 0.3), (0, 2, 0.3), (-2, 0, 0.3), (0, -2, 0.3), (1.2, 1.2, 1.2), (0.1, 0.1, 2)]
    poses = torch.stack([_look_at(e) for e in eyes])
    width = 48
    focal = focal_from_fov(width, 2 * math.atan(0.5))
    masks = _silhouettes(poses, width, focal)
    centers = cell_centers(32, LO, HI)
    exact = carve_from_masks(poses, masks, Intrinsics.centred(width, width, focal), UNIT_BOX, resolution=32, mask_dilation_px=0, dilation=0)
    # undilated masks can carve up to a pixel (0.04 here) into the silhouette
    assert exact.occupied.reshape(-1)[centers.norm(dim=-1) < 0.2].all()
    assert exact.fraction < 0.08  # the sphere is 6.5% of the box; six views leave a thin margin
    grid = carve_from_masks(poses, masks, Intrinsics.centred(width, width, focal), UNIT_BOX, resolution=32)  # default safety margins
    occ = grid.occupied.reshape(-1)
    assert occ[centers.norm(dim=-1) < 0.25].all()
    assert exact.fraction < grid.fraction < 0.3
    corner_rays = ray_box_intersection(torch.zeros(1, 3), torch.ones(1, 3) / math.sqrt(3), LO, HI)
    assert corner_rays[2].all()
    assert not grid.lookup(torch.tensor([[0.45, 0.45, 0.45], [-0.45, -0.45, -0.45]])).any()
