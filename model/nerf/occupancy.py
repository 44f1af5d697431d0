"""Per-object occupancy grid: which cells of the scene box can hold matter.

Built once per NeRF (from its density, or carved from training masks as a visual hull) and kept
with it, so renderers skip empty space without evaluating the field there, and the occupied cells'
bounding box gives a tight per-object box to march through. While a field is being optimised
(fits, test-time optimisation, finetuning) :class:`MaintainedGrid` keeps the grid in step with the
field's own density, InstantNGP style; masks, when a dataset has them, only speed it up.

Densities are per unit length of the scene box's unit cube (``model.nerf.scene``), so thresholds
depend on the grid's resolution only, not on the scene's world size.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from model.nerf.rays import Intrinsics, project
from model.nerf.scene import SceneBox


@dataclass
class OccupancyGrid:
    """Boolean grid ``occupied [G, G, G]`` indexed ``[x, y, z]`` over the box ``[box_min, box_max]``."""

    occupied: torch.Tensor
    box_min: torch.Tensor
    box_max: torch.Tensor

    @classmethod
    def full(cls, scene: SceneBox, resolution: int = 64, device=None) -> "OccupancyGrid":
        """Every cell occupied: the grid of a field nothing is known about yet."""
        lo, hi = scene.tensors(device)
        return cls(torch.ones(resolution, resolution, resolution, dtype=torch.bool, device=device), lo, hi)

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


def density_threshold(resolution: int, cell_opacity: float) -> float:
    """Density below which a cell, crossed along its longest side (``1 / resolution`` of the unit
    cube), is more transparent than ``1 - cell_opacity``."""
    return -torch.log1p(torch.tensor(-cell_opacity)).item() * resolution


@torch.no_grad()
def max_cell_density(
    density_fn: Callable[[torch.Tensor], torch.Tensor],
    resolution: int,
    box_min: torch.Tensor,
    box_max: torch.Tensor,
    *,
    cells: torch.Tensor | None = None,
    samples_per_cell: int = 2,
    include_centre: bool = True,
    generator: torch.Generator | None = None,
    chunk: int = 1 << 16,
) -> torch.Tensor:
    """Largest density seen per cell, ``[G, G, G]``, over ``samples_per_cell`` points: the centre
    (when ``include_centre``) and uniform jittered points inside the cell.

    ``cells`` (a boolean ``[G, G, G]`` mask) limits the evaluation to those cells; the others read 0.
    """
    centers = cell_centers(resolution, box_min, box_max)
    index = cells.reshape(-1).nonzero().squeeze(1) if cells is not None else None
    if index is not None:
        centers = centers[index]
    size = (box_max - box_min) / resolution
    best = torch.zeros(centers.shape[0], device=centers.device)
    for sample in range(samples_per_cell):
        if sample == 0 and include_centre:
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
    scene: SceneBox,
    *,
    resolution: int = 64,
    cell_opacity: float = 2e-3,
    dilation: int = 1,
    samples_per_cell: int = 2,
    generator: torch.Generator | None = None,
    device=None,
) -> OccupancyGrid:
    """Occupancy of a NeRF: cells whose peak density makes them more opaque than ``cell_opacity``.

    ``density_fn`` maps world points ``[N, 3]`` to densities ``[N]`` (see ``world_density``)."""
    box_min, box_max = scene.tensors(device)
    dens = max_cell_density(density_fn, resolution, box_min, box_max, samples_per_cell=samples_per_cell, generator=generator)
    thr = density_threshold(resolution, cell_opacity)
    return OccupancyGrid(dilate(dens > thr, dilation), box_min, box_max)


def _cells_in_views(c2w: torch.Tensor, cameras: Sequence[Intrinsics], centers: torch.Tensor):
    """For each view: the pixel of every cell centre ``(px, py)`` (clamped into the image) and
    whether the view sees the centre (in front of the camera, inside its image)."""
    for pose, camera in zip(c2w, cameras):
        x, y, depth = project((centers - pose[:3, 3]) @ pose[:3, :3], camera)  # rot is orthonormal
        inside = (depth > 1e-6) & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        yield x.clamp(0, camera.width - 1).long(), y.clamp(0, camera.height - 1).long(), inside


@torch.no_grad()
def carve_from_masks(
    c2w: torch.Tensor,
    masks: torch.Tensor,
    cameras: Intrinsics | Sequence[Intrinsics],
    scene: SceneBox,
    *,
    resolution: int = 64,
    mask_dilation_px: int = 2,
    dilation: int = 1,
) -> OccupancyGrid:
    """Visual hull: a cell stays occupied only if every view sees it inside the object's silhouette.

    ``masks [V, H, W]`` are booleans (alpha > 0), ``cameras`` one pinhole for all views or one
    per view; the masks are dilated by a few pixels and the hull by
    ``dilation`` cells, so the carving never removes a surface the images show. Cells that project
    outside a view are not carved by that view.
    """
    views, height, width = masks.shape
    cameras = [cameras] * views if isinstance(cameras, Intrinsics) else list(cameras)
    if len(cameras) != views or any((c.height, c.width) != (height, width) for c in cameras):
        raise ValueError(f"need one camera of {width}x{height} per mask, got {len(cameras)} for {views} masks")
    box_min, box_max = scene.tensors(masks.device)
    k = 2 * mask_dilation_px + 1
    grown = F.max_pool2d(masks[:, None].float(), kernel_size=k, stride=1, padding=mask_dilation_px)[:, 0] > 0
    keep = torch.ones(resolution**3, dtype=torch.bool, device=masks.device)
    for v, (px, py, inside) in enumerate(_cells_in_views(c2w, cameras, cell_centers(resolution, box_min, box_max))):
        keep &= ~(inside & ~grown[v, py, px])  # carve cells a view sees outside the silhouette
    occupied = dilate(keep.reshape(resolution, resolution, resolution), dilation)
    return OccupancyGrid(occupied, box_min, box_max)


@torch.no_grad()
def visible_cells(c2w: torch.Tensor, cameras: Intrinsics | Sequence[Intrinsics], scene: SceneBox, resolution: int = 64) -> OccupancyGrid:
    """Cells whose centre some view sees (in front of the camera, inside its image), as
    InstantNGP marks untrained cells: no training ray constrains the others, so they stay empty."""
    cameras = [cameras] * c2w.shape[0] if isinstance(cameras, Intrinsics) else list(cameras)
    box_min, box_max = scene.tensors(c2w.device)
    seen = torch.zeros(resolution**3, dtype=torch.bool, device=c2w.device)
    for _, _, inside in _cells_in_views(c2w, cameras, cell_centers(resolution, box_min, box_max)):
        seen |= inside
    return OccupancyGrid(seen.reshape(resolution, resolution, resolution), box_min, box_max)


@dataclass
class OccupancyConfig:
    """How a :class:`MaintainedGrid` follows a field during optimisation."""

    resolution: int = 64
    update_every: int = 16
    warmup_steps: int = 64
    decay: float = 0.95
    cell_opacity: float = 2e-3
    dilation: int = 1
    seed: int = 0


class MaintainedGrid:
    """The occupancy grid of a field being optimised, InstantNGP style.

    It starts fully occupied, or as ``limit`` (the cells the training views see, or the visual
    hull when masks give one), or as ``start`` when the field's density is already known (a
    generated NeRF's own grid at the start of test-time optimisation). From
    ``warmup_steps`` on, every ``update_every`` steps, :meth:`step` evaluates the density at one
    jittered point of every candidate cell, keeps a decaying maximum per cell (``decay``), and
    marks the cells above the threshold of ``cell_opacity``, grown by ``dilation`` cells. Cells
    outside ``limit`` stay empty whatever their density. The jitter draws from the grid's own
    generator seeded by ``cfg.seed``: a run gives the same grids every time, and updates leave the
    optimiser's random stream alone.
    """

    def __init__(self, scene: SceneBox, cfg: OccupancyConfig, *, limit: OccupancyGrid | None = None,
                 start: OccupancyGrid | None = None, device=None):
        for name, given in (("limiting", limit), ("starting", start)):
            if given is not None and given.resolution != cfg.resolution:
                raise ValueError(f"the {name} grid has resolution {given.resolution}, the maintained grid {cfg.resolution}")
        self.cfg = cfg
        self.scene = scene
        self.limit = limit.to(device) if limit is not None else None
        if start is not None:
            self.grid = start.to(device)
        else:
            self.grid = self.limit if self.limit is not None else OccupancyGrid.full(scene, cfg.resolution, device)
        self.cell_density = torch.full(self.grid.occupied.shape, float("inf"), device=device)
        self.threshold = density_threshold(cfg.resolution, cfg.cell_opacity)
        self.generator = torch.Generator(device=device).manual_seed(cfg.seed)

    def due(self, step: int) -> bool:
        return step >= self.cfg.warmup_steps and (step - self.cfg.warmup_steps) % self.cfg.update_every == 0

    def step(self, step: int, density_fn: Callable[[torch.Tensor], torch.Tensor]) -> bool:
        """Update the grid if ``step`` is an update step; returns whether it did."""
        if not self.due(step):
            return False
        self.update(density_fn)
        return True

    @torch.no_grad()
    def update(self, density_fn: Callable[[torch.Tensor], torch.Tensor]) -> OccupancyGrid:
        """Fold the field's current density (``density_fn``: world points ``[N, 3]`` -> ``[N]``) into the grid."""
        fresh = max_cell_density(
            density_fn,
            self.cfg.resolution,
            self.grid.box_min,
            self.grid.box_max,
            cells=self.limit.occupied if self.limit is not None else None,
            samples_per_cell=1,
            include_centre=False,
            generator=self.generator,
        )
        decayed = torch.where(torch.isinf(self.cell_density), fresh, self.cell_density * self.cfg.decay)
        self.cell_density = torch.maximum(decayed, fresh)
        occupied = dilate(self.cell_density > self.threshold, self.cfg.dilation)
        if self.limit is not None:
            occupied &= self.limit.occupied
        self.grid = OccupancyGrid(occupied, self.grid.box_min, self.grid.box_max)
        return self.grid
