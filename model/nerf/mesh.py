"""Mesh extraction from a density field, and mesh export.

The density is sampled on a regular grid over a box in bounded-memory chunks, then
``skimage.measure.marching_cubes`` (scikit-image: maintained, pip-only, Lewiner's variant with
consistent topology) extracts the iso-surface at a density threshold, following torch-ngp's
``save_mesh``. ``trimesh`` holds the result, cleans it and exports GLB / PLY / OBJ.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import trimesh
from skimage.measure import marching_cubes

from model.nerf.fields import Field, FieldParams, world_color, world_density
from model.nerf.occupancy import OccupancyGrid
from model.nerf.scene import SceneBox

# torch-ngp's save_mesh threshold: density 10 per unit of the scene box is an opacity of
# 1 - exp(-10 * 0.1) = 63% over a tenth of the box, a clear surface without catching haze.
DEFAULT_THRESHOLD = 10.0

# Formats ``export_mesh`` and ``mesh_bytes`` write, with what each keeps: all keep geometry; GLB
# and PLY keep per-vertex RGBA colours (OBJ writes them as a non-standard extension only some
# readers accept).
SUPPORTED_FORMATS = ("glb", "ply", "obj")


def _grid_points(start: int, stop: int, resolution: int, box_min: torch.Tensor,
                 step: torch.Tensor) -> torch.Tensor:
    """World positions of flat grid indices ``[start, stop)`` of a ``resolution^3`` grid, x-major."""
    idx = torch.arange(start, stop, device=box_min.device, dtype=torch.int64)
    ijk = torch.stack((idx // (resolution * resolution), (idx // resolution) % resolution,
                       idx % resolution), dim=-1)
    return box_min + ijk.to(box_min.dtype) * step


def density_grid(density_fn: Callable[[torch.Tensor], torch.Tensor], box_min, box_max,
                 resolution: int = 128, chunk: int = 2**16, device=None) -> np.ndarray:
    """``density_fn`` sampled at ``resolution^3`` points spanning ``[box_min, box_max]`` (corners
    included), as a float32 array indexed ``[x, y, z]``.

    Points go to ``density_fn`` as ``[n <= chunk, 3]`` float32 tensors on ``device`` (default: the
    device of ``box_min`` when it is a tensor, else CPU); only one chunk is on the device at a time.
    """
    if resolution < 2:
        raise ValueError(f"resolution must be at least 2, got {resolution}")
    if chunk < 1:
        raise ValueError(f"chunk must be positive, got {chunk}")
    if device is None:
        device = box_min.device if isinstance(box_min, torch.Tensor) else torch.device("cpu")
    lo = torch.as_tensor(box_min, dtype=torch.float32, device=device).reshape(-1)
    hi = torch.as_tensor(box_max, dtype=torch.float32, device=device).reshape(-1)
    if lo.shape != (3,) or hi.shape != (3,):
        raise ValueError(f"box_min and box_max must have 3 coordinates, got {tuple(lo.shape)}, {tuple(hi.shape)}")
    if not (hi > lo).all():
        raise ValueError(f"box_max must exceed box_min on every axis, got {lo.tolist()} and {hi.tolist()}")
    step = (hi - lo) / (resolution - 1)
    total = resolution**3
    values = np.empty(total, dtype=np.float32)
    for start in range(0, total, chunk):
        stop = min(start + chunk, total)
        sigma = density_fn(_grid_points(start, stop, resolution, lo, step))
        sigma = torch.as_tensor(sigma).reshape(-1)
        if sigma.numel() != stop - start:
            raise ValueError(f"density_fn returned {sigma.numel()} values for {stop - start} points")
        values[start:stop] = sigma.detach().float().cpu().numpy()
    if np.isnan(values).any():
        raise ValueError("density_fn returned NaN")
    return values.reshape(resolution, resolution, resolution)


def _drop_small_components(mesh: trimesh.Trimesh, min_component_fraction: float) -> None:
    """Remove connected components whose area is below ``min_component_fraction`` of the largest's."""
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    area = np.bincount(labels, weights=mesh.area_faces)
    keep = area >= min_component_fraction * area.max()
    mesh.update_faces(keep[labels])
    mesh.remove_unreferenced_vertices()


def _vertex_colors(color_fn: Callable[[torch.Tensor], torch.Tensor], vertices: np.ndarray,
                   chunk: int, device) -> np.ndarray:
    """``color_fn`` at the vertices, as uint8 RGBA with opaque alpha."""
    rgba = np.full((len(vertices), 4), 255, dtype=np.uint8)
    for start in range(0, len(vertices), chunk):
        pts = torch.as_tensor(vertices[start:start + chunk], dtype=torch.float32, device=device)
        rgb = torch.as_tensor(color_fn(pts)).detach().float().cpu()
        if rgb.shape != (len(pts), 3):
            raise ValueError(f"color_fn must return [N, 3], got {tuple(rgb.shape)} for N={len(pts)}")
        rgba[start:start + len(pts), :3] = (rgb.nan_to_num(0.0).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()
    return rgba


@torch.no_grad()
def extract_mesh(density_fn: Callable[[torch.Tensor], torch.Tensor], box_min, box_max,
                 resolution: int = 128, threshold: float = DEFAULT_THRESHOLD,
                 color_fn: Callable[[torch.Tensor], torch.Tensor] | None = None,
                 chunk: int = 2**16, min_component_fraction: float = 0.0,
                 device=None) -> trimesh.Trimesh:
    """The ``threshold`` iso-surface of ``density_fn`` over ``[box_min, box_max]``.

    ``density_fn(points [N, 3]) -> [N]`` is sampled on a ``resolution^3`` grid (see
    ``density_grid``); marching cubes places vertices by linear interpolation between grid
    samples, so they are accurate well within one cell (``(box_max - box_min) / (resolution - 1)``).
    Faces wind counter-clockwise seen from low density (outward normals). Surfaces reaching the
    box boundary stay open there.

    With ``color_fn(points [N, 3]) -> [N, 3]`` in [0, 1], vertex colours are set (uint8 RGBA,
    opaque), evaluated at the final vertices in chunks.

    Cleaning: duplicate vertices merged, degenerate faces and unreferenced vertices removed, and,
    if ``min_component_fraction > 0``, connected components with less than that fraction of the
    largest component's area dropped (NeRF floaters). The default 0 keeps everything, which is what
    a geometry metric should see.

    A grid that never crosses the threshold gives an empty mesh (``mesh.is_empty``), not an error.
    """
    if not 0.0 <= min_component_fraction <= 1.0:
        raise ValueError(f"min_component_fraction must be in [0, 1], got {min_component_fraction}")
    if device is None:
        device = box_min.device if isinstance(box_min, torch.Tensor) else torch.device("cpu")
    grid = density_grid(density_fn, box_min, box_max, resolution, chunk, device)
    if not grid.min() < threshold < grid.max():
        return trimesh.Trimesh()
    lo = np.asarray(torch.as_tensor(box_min).cpu(), dtype=np.float64).reshape(3)
    hi = np.asarray(torch.as_tensor(box_max).cpu(), dtype=np.float64).reshape(3)
    # Infinite densities (an untruncated exp) would make interpolated vertices NaN; any finite
    # value far above the threshold places the vertex the same way.
    grid = np.minimum(grid, np.float32(np.finfo(np.float32).max / 4))
    # 'descent': density is high inside the object, so normals point towards decreasing density.
    verts, faces, _, _ = marching_cubes(grid, level=threshold, gradient_direction="ascent")
    verts = lo + verts * ((hi - lo) / (resolution - 1))
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if min_component_fraction > 0.0 and len(mesh.faces):
        _drop_small_components(mesh, min_component_fraction)
    if color_fn is not None and len(mesh.vertices):
        mesh.visual.vertex_colors = _vertex_colors(color_fn, np.asarray(mesh.vertices), chunk, device)
    return mesh


def _check_format(fmt: str) -> str:
    name = fmt.lower().lstrip(".")
    if name not in SUPPORTED_FORMATS:
        raise ValueError(f"unsupported mesh format {fmt!r}; supported: {', '.join(SUPPORTED_FORMATS)}")
    return name


# (x, y, z) -> (x, z, -y): a quarter turn about X from the project's Z-up world to glTF's Y-up
Z_UP_TO_Y_UP = trimesh.transformations.rotation_matrix(-np.pi / 2, [1.0, 0.0, 0.0])


def mesh_bytes(mesh: trimesh.Trimesh, format: str) -> bytes:
    """``mesh`` encoded as ``format`` (``glb``, ``ply`` binary, or ``obj``), ready to stream.

    GLB is written Y-up, as glTF specifies (viewers would show a Z-up mesh lying on its back);
    PLY and OBJ keep the project's Z-up world coordinates. An empty mesh still encodes (a file
    with no geometry), so a caller can serve it.
    """
    fmt = _check_format(format)
    if fmt == "glb" and len(mesh.vertices):
        mesh = mesh.copy()
        mesh.apply_transform(Z_UP_TO_Y_UP)
    if fmt == "obj":
        # OBJ is text: write vertex colours only if present, and no normals (readers recompute them).
        data = mesh.export(file_type="obj", include_normals=False,
                           include_color=mesh.visual.kind == "vertex")
    else:
        data = mesh.export(file_type=fmt)
    return data.encode("utf-8") if isinstance(data, str) else bytes(data)


def export_mesh(mesh: trimesh.Trimesh, path, format: str | None = None) -> Path:
    """Write ``mesh`` to ``path`` as ``format``, by default the path's suffix (.glb, .ply, .obj)."""
    path = Path(path)
    if format is None and not path.suffix:
        raise ValueError(f"cannot tell the format of {str(path)!r}; supported: {', '.join(SUPPORTED_FORMATS)}")
    path.write_bytes(mesh_bytes(mesh, format if format is not None else path.suffix))
    return path


def sample_surface(mesh: trimesh.Trimesh, n_points: int, seed: int = 0) -> np.ndarray:
    """``n_points`` points uniform on the surface (faces chosen by area), reproducible by ``seed``.

    An empty mesh, or one of zero area, gives ``[0, 3]``.
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if n_points <= 0:
        raise ValueError(f"n_points must be positive, got {n_points}")
    if mesh.is_empty or not mesh.area > 0.0:
        return np.zeros((0, 3))
    if not np.isfinite(mesh.vertices).all():
        raise ValueError("mesh vertices contain NaN or infinite coordinates")
    points, _ = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    return np.asarray(points, dtype=np.float64)


def field_mesh(params: FieldParams, field_cfg: Field, grid: OccupancyGrid, scene: SceneBox, resolution: int = 128) -> trimesh.Trimesh:
    """Marching-cubes mesh of a NeRF over its occupied box, with vertex colours, in world coordinates.

    Density in cells the occupancy grid marks empty is taken as zero, as the renderer does, so the
    mesh shows the NeRF that renders and not the haze left where no ray constrains it. Densities
    are per unit of the scene box, so the threshold means the same at any world scale.
    """
    box = grid.tight_box()
    if box is None:
        return trimesh.Trimesh()
    density = world_density(params, field_cfg, scene)

    def rendered_density(points: torch.Tensor) -> torch.Tensor:
        return density(points) * grid.lookup(points)

    return extract_mesh(rendered_density, box[0], box[1], resolution=resolution, color_fn=world_color(params, field_cfg, scene))
