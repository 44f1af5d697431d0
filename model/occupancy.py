"""Per-object occupancy grid: which cells of the scene box can hold matter.

Built once per NeRF (from its density, or carved from training masks as a visual hull) and kept
with it, so renderers skip empty space without evaluating the field there, and the occupied cells'
bounding box gives a tight per-object box to march through.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class OccupancyGrid:
    """Boolean grid ``occupied [G, G, G]`` indexed ``[x, y, z]`` over the box ``[box_min, box_max]``."""

    occupied: torch.Tensor
    box_min: torch.Tensor
    box_max: torch.Tensor

    @property
    def resolution(self) -> int:
        return self.occupied.shape[0]

    @property
    def fraction(self) -> float:
        return float(self.occupied.float().mean())

    def to(self, device) -> "OccupancyGrid":
        return OccupancyGrid(self.occupied.to(device), self.box_min.to(device), self.box_max.to(device))

    def cell_index(self, points: torch.Tensor) -> torch.Tensor:
        """Flat cell index of ``points [..., 3]`` (clamped into the grid)."""
        g = self.resolution
        cell = ((points - self.box_min) / (self.box_max - self.box_min) * g).floor().long().clamp_(0, g - 1)
        return (cell[..., 0] * g + cell[..., 1]) * g + cell[..., 2]

    def lookup(self, points: torch.Tensor) -> torch.Tensor:
        """Whether each point of ``points [..., 3]`` lies in an occupied cell; outside the box is empty."""
        g = self.resolution
        cell = (points - self.box_min) * (g / (self.box_max - self.box_min))
        inside = ((cell >= 0) & (cell <= g)).all(dim=-1)
        # truncation is floor for the points that count (inside the box); the clamp keeps the rest
        # (and x = G on the far faces) in range
        cell = cell.long().clamp_(0, g - 1)
        return self.occupied.reshape(-1)[(cell[..., 0] * g + cell[..., 1]) * g + cell[..., 2]] & inside

    def tight_box(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Bounding box of the occupied cells, or ``None`` when nothing is occupied."""
        idx = self.occupied.nonzero()
        if idx.numel() == 0:
            return None
        size = (self.box_max - self.box_min) / self.resolution
        lo = self.box_min + idx.amin(dim=0).to(size.dtype) * size
        hi = self.box_min + (idx.amax(dim=0) + 1).to(size.dtype) * size
        return lo, hi

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"occupied": self.occupied.to(torch.uint8), "box_min": self.box_min, "box_max": self.box_max}

    @classmethod
    def from_state_dict(cls, state: dict[str, torch.Tensor]) -> "OccupancyGrid":
        return cls(state["occupied"].bool(), state["box_min"].float(), state["box_max"].float())


def cell_centers(resolution: int, box_min: torch.Tensor, box_max: torch.Tensor) -> torch.Tensor:
    """World positions of all cell centres, ``[G**3, 3]`` in flat-index order."""
    axis = (torch.arange(resolution, device=box_min.device, dtype=box_min.dtype) + 0.5) / resolution
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    return box_min + grid * (box_max - box_min)


def dilate(occupied: torch.Tensor, cells: int = 1) -> torch.Tensor:
    """Grow the occupied set by ``cells`` in every direction (a safety margin for thin parts)."""
    if cells <= 0:
        return occupied
    k = 2 * cells + 1
    grown = F.max_pool3d(occupied[None, None].float(), kernel_size=k, stride=1, padding=cells)
    return grown[0, 0] > 0


def density_threshold(resolution: int, box_min: torch.Tensor, box_max: torch.Tensor, cell_opacity: float) -> float:
    """Density below which a cell, crossed along its side, is more transparent than ``1 - cell_opacity``."""
    cell = float((box_max - box_min).max()) / resolution
    return -torch.log1p(torch.tensor(-cell_opacity)).item() / cell


@torch.no_grad()
def max_cell_density(
    density_fn: Callable[[torch.Tensor], torch.Tensor],
    resolution: int,
    box_min: torch.Tensor,
    box_max: torch.Tensor,
    *,
    cells: torch.Tensor | None = None,
    samples_per_cell: int = 2,
    generator: torch.Generator | None = None,
    chunk: int = 1 << 16,
) -> torch.Tensor:
    """Largest density seen per cell, ``[G, G, G]``: at the centre plus jittered points inside it.

    ``cells`` (a boolean ``[G, G, G]`` mask) limits the evaluation to those cells; the others read 0.
    """
    centers = cell_centers(resolution, box_min, box_max)
    index = cells.reshape(-1).nonzero().squeeze(1) if cells is not None else None
    if index is not None:
        centers = centers[index]
    size = (box_max - box_min) / resolution
    best = torch.zeros(centers.shape[0], device=centers.device)
    for sample in range(samples_per_cell):
        if sample == 0:
            points = centers
        else:
            jitter = torch.rand(centers.shape, generator=generator, device=centers.device) - 0.5
            points = centers + jitter * size
        for start in range(0, points.shape[0], chunk):
            part = density_fn(points[start : start + chunk]).float()
            best[start : start + chunk] = torch.maximum(best[start : start + chunk], part)
    if index is not None:
        best = torch.zeros(resolution**3, device=best.device).index_copy(0, index, best)
    return best.reshape(resolution, resolution, resolution)


def grid_from_density(
    density_fn: Callable[[torch.Tensor], torch.Tensor],
    box_min: torch.Tensor,
    box_max: torch.Tensor,
    *,
    resolution: int = 64,
    cell_opacity: float = 2e-3,
    dilation: int = 1,
    samples_per_cell: int = 2,
    generator: torch.Generator | None = None,
) -> OccupancyGrid:
    """Occupancy of a NeRF: cells whose peak density makes them more opaque than ``cell_opacity``."""
    dens = max_cell_density(density_fn, resolution, box_min, box_max, samples_per_cell=samples_per_cell, generator=generator)
    thr = density_threshold(resolution, box_min, box_max, cell_opacity)
    return OccupancyGrid(dilate(dens > thr, dilation), box_min, box_max)


@torch.no_grad()
def carve_from_masks(
    c2w: torch.Tensor,
    masks: torch.Tensor,
    focal: float,
    box_min: torch.Tensor,
    box_max: torch.Tensor,
    *,
    resolution: int = 64,
    mask_dilation_px: int = 2,
    dilation: int = 1,
) -> OccupancyGrid:
    """Visual hull: a cell stays occupied only if every view sees it inside the object's silhouette.

    ``masks [V, H, W]`` are booleans (alpha > 0); they are dilated by a few pixels and the hull by
    ``dilation`` cells, so the carving never removes a surface the images show. Cells that project
    outside a view are not carved by that view.
    """
    views, height, width = masks.shape
    k = 2 * mask_dilation_px + 1
    grown = F.max_pool2d(masks[:, None].float(), kernel_size=k, stride=1, padding=mask_dilation_px)[:, 0] > 0
    centers = cell_centers(resolution, box_min, box_max)
    keep = torch.ones(centers.shape[0], dtype=torch.bool, device=centers.device)
    for v in range(views):
        rot, pos = c2w[v, :3, :3], c2w[v, :3, 3]
        cam = (centers - pos) @ rot  # world -> camera frame (rot is orthonormal)
        depth = -cam[:, 2]
        front = depth > 1e-6
        x = cam[:, 0] / depth.clamp_min(1e-6) * focal + 0.5 * width
        y = -cam[:, 1] / depth.clamp_min(1e-6) * focal + 0.5 * height
        inside = front & (x >= 0) & (x < width) & (y >= 0) & (y < height)
        px = x.clamp(0, width - 1).long()
        py = y.clamp(0, height - 1).long()
        seen_empty = inside & ~grown[v, py, px]
        keep &= ~seen_empty
    occupied = dilate(keep.reshape(resolution, resolution, resolution), dilation)
    return OccupancyGrid(occupied, box_min, box_max)

