"""A category of objects held in memory for training a prior: images, poses, occupancy, instances.

Images are kept as uint8 (a quarter of float32: 260 instances x 91 views at 128x128 take 1.6 GB)
and turned into rays only for the pixels a step draws. Colour variants of one mesh (dataset
entries sharing an ``extra.shape_id``) share a shape index, and their training occupancy grid.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch
import trimesh
from tqdm import tqdm

from model.data.dataset import DatasetError, ObjectEntry, load_index, load_views
from model.nerf.mesh import sample_surface
from model.nerf.occupancy import OccupancyGrid, carve_from_masks, dilate
from model.nerf.rays import Intrinsics, camera_directions
from model.nerf.scene import SceneBox

log = logging.getLogger(__name__)


@dataclass
class Instance:
    """One training instance: an index entry and which shape it has."""

    id: str
    caption: str
    shape_id: str
    shape_index: int

    def to_json(self) -> dict:
        return {"id": self.id, "caption": self.caption, "shape_id": self.shape_id, "shape_index": self.shape_index}


@dataclass
class CategoryData:
    """Training views of every instance: ``images [N, V, H, W, 4]`` uint8, ``c2w [N, V, 4, 4]``,
    one ``camera`` and one ``scene`` box shared by the whole category."""

    root: Path
    instances: list[Instance]
    images: torch.Tensor
    c2w: torch.Tensor
    camera: Intrinsics
    scene: SceneBox

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    @property
    def shape_index(self) -> list[int]:
        return [inst.shape_index for inst in self.instances]

    @property
    def shapes(self) -> int:
        return max(self.shape_index) + 1

    def rays(self, instance: int, pixels: torch.Tensor, directions_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rays and straight-alpha RGBA targets of flat pixel indices ``[R]`` over the views of one instance."""
        per_view = self.width * self.height
        view, pixel = pixels // per_view, pixels % per_view
        c2w = self.c2w[instance, view]
        directions = (c2w[:, :3, :3] @ directions_cam[pixel][..., None]).squeeze(-1)
        directions = directions / directions.norm(dim=-1, keepdim=True)
        rgba = self.images[instance].reshape(-1, 4)[pixels].float() / 255.0
        return c2w[:, :3, 3], directions, rgba

    def camera_directions(self, device=None) -> torch.Tensor:
        return camera_directions(self.camera, device=device).reshape(-1, 3)


def select_instances(root: Path, split: str = "train", limit: int | None = None) -> list[ObjectEntry]:
    entries = [e for e in load_index(root) if e.split == split]
    if not entries:
        raise DatasetError(f"{root} has no objects in the {split!r} split; build a dataset with more objects")
    entries.sort(key=lambda e: e.id)
    return entries[:limit] if limit else entries


def load_category(root: Path, split: str = "train", limit: int | None = None, progress: bool = True) -> CategoryData:
    """Every instance of one object split with its training views (all share one camera and scene box)."""
    root = Path(root)
    entries = select_instances(root, split, limit)
    shape_ids: dict[str, int] = {}
    instances, images, poses = [], [], []
    camera = scene = None
    for entry in tqdm(entries, desc="loading views", unit="object", disable=not progress):
        views = load_views(root / entry.id, split="train")
        if camera is None:
            camera, scene = views.camera, views.scene
        elif views.camera != camera:
            raise DatasetError(f"{entry.id} has camera {views.camera}; every object of a category must share one camera, {camera}")
        elif views.scene != scene:
            raise DatasetError(f"{entry.id} has scene box {views.scene.to_aabb()}; every object of a category must share one, {scene.to_aabb()}")
        if images and views.images.shape[0] != images[0].shape[0]:
            raise DatasetError(f"{entry.id} has {views.images.shape[0]} training views, others {images[0].shape[0]}; render all objects with the same --views")
        rgba = views.images if views.images.shape[-1] == 4 else torch.cat([views.images, torch.ones_like(views.images[..., :1])], -1)
        images.append((rgba * 255.0).round().to(torch.uint8))
        poses.append(views.c2w)
        shape_id = str(entry.extra.get("shape_id", entry.id))
        index = shape_ids.setdefault(shape_id, len(shape_ids))
        instances.append(Instance(entry.id, entry.caption, shape_id, index))
    log.info("loaded %d instances of %d shapes from %s", len(instances), len(shape_ids), root)
    return CategoryData(root, instances, torch.stack(images), torch.stack(poses), camera, scene)


OCCUPANCY_SOURCES = ("hull", "mesh", "box")


def shape_grids(data: CategoryData, resolution: int = 64, progress: bool = True, source: str = "hull") -> torch.Tensor:
    """Training occupancy of every shape, ``[shapes, G, G, G]`` bool, from its first instance.

    Training marches rays only through these cells; colour variants share them. ``source``:
    - ``hull``: the visual hull carved from the training masks (needs nothing but the images);
    - ``mesh``: cells within one cell of the ground-truth surface (``mesh.ply``; tighter than the
      hull in concavities, but only for datasets that ship meshes);
    - ``box``: every cell (no empty-space skipping; the reference the others are measured against).
    """
    if source not in OCCUPANCY_SOURCES:
        raise ValueError(f"unknown occupancy source {source!r}; choose one of {OCCUPANCY_SOURCES}")
    first = {}
    for n, inst in enumerate(data.instances):
        first.setdefault(inst.shape_index, n)
    grids = []
    for shape in tqdm(range(data.shapes), desc=f"occupancy ({source})", unit="shape", disable=not progress):
        n = first[shape]
        if source == "box":
            grids.append(torch.ones(resolution, resolution, resolution, dtype=torch.bool))
        elif source == "mesh":
            grids.append(surface_cells(data.root / data.instances[n].id / "mesh.ply", resolution, data.scene))
        else:
            masks = data.images[n, ..., 3] > 0
            grids.append(carve_from_masks(data.c2w[n], masks, data.camera, data.scene, resolution=resolution).occupied)
    return torch.stack(grids)


def surface_cells(mesh_path: Path, resolution: int, scene: SceneBox, points: int = 200_000) -> torch.Tensor:
    """Cells within one cell of a mesh's surface: dense surface samples, marked, then dilated."""
    if not mesh_path.is_file():
        raise DatasetError(f"{mesh_path} is missing: occupancy from meshes needs each object's ground-truth mesh; use the hull instead")
    samples = torch.from_numpy(sample_surface(trimesh.load(mesh_path, force="mesh", process=False), points)).float()
    cells = (scene.to_unit(samples) * resolution).floor().long().clamp_(0, resolution - 1)
    occupied = torch.zeros(resolution, resolution, resolution, dtype=torch.bool)
    occupied[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    return dilate(occupied, 1)


def grid_of(occupied: torch.Tensor, scene: SceneBox, device=None) -> OccupancyGrid:
    lo, hi = scene.tensors(device)
    return OccupancyGrid(occupied.to(device), lo, hi)


def free_space_grids(grids: torch.Tensor, margin: int = 1) -> torch.Tensor:
    """Each shape's hull grown by ``margin`` cells, ``[shapes, G, G, G]``: what lies outside is
    surely empty. Computed once per run (a 3D max-pool per shape is too slow to repeat every step)."""
    return torch.stack([dilate(grid, margin) for grid in grids]) if len(grids) else grids


def free_space_points(grown: torch.Tensor, scene: SceneBox, count: int, generator: torch.Generator) -> torch.Tensor:
    """Up to ``count`` uniform points of the scene box in cells empty in ``grown`` (a hull grown by
    a margin, see ``free_space_grids``); world coordinates ``[M, 3]``."""
    points = scene.from_unit(torch.rand(count, 3, generator=generator, device=grown.device))
    return points[~grid_of(grown, scene, grown.device).lookup(points)]
