"""Quality of a fitted (or generated) NeRF: held-out renders, PSNR/SSIM, mesh and Chamfer distance."""

from __future__ import annotations

import time

import torch
import trimesh

from model.field import FieldConfig, FieldParams, color, density
from model.fit import scene_box, unit_density_fn
from model.mesh import extract_mesh
from model.metrics import mesh_chamfer, psnr, ssim
from model.occupancy import OccupancyGrid
from model.renderer import RenderConfig, render_image


def composite_over(rgba: torch.Tensor, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """Straight-alpha RGBA ``[..., 4]`` over a constant background -> RGB ``[..., 3]``."""
    bg = torch.tensor(background, dtype=rgba.dtype, device=rgba.device)
    return rgba[..., :3] * rgba[..., 3:] + bg * (1 - rgba[..., 3:])


def render_views(params: FieldParams, field_cfg: FieldConfig, views, cfg: RenderConfig, grid: OccupancyGrid | None):
    """Render every view of ``views``; returns images ``[V, H, W, 3]`` and median ms per image."""
    images, times = [], []
    for c2w in views.c2w:
        start = time.perf_counter()
        out = render_image(params, field_cfg, c2w, views.width, views.height, views.focal, cfg, grid=grid)
        times.append(1000 * (time.perf_counter() - start))
        images.append(out["rgb"])
    return torch.stack(images), float(torch.tensor(times).median())


def color_fn_for(params: FieldParams, field_cfg: FieldConfig, device):
    """Vertex colours: the colour net seen from straight above (the field's view dependence is weak)."""
    lo, hi = scene_box(device)

    def fn(points: torch.Tensor) -> torch.Tensor:
        unit = ((points - lo) / (hi - lo)).clamp(0, 1)[None]
        _, geo = density(params, unit, field_cfg)
        down = torch.tensor([0.0, 0.0, -1.0], device=points.device).expand_as(points)[None]
        return color(params, geo, down, field_cfg)[0]

    return fn


def field_mesh(params: FieldParams, field_cfg: FieldConfig, grid: OccupancyGrid, resolution: int = 128) -> trimesh.Trimesh:
    """Marching-cubes mesh of the field over its occupied box, with vertex colours.

    Density in cells the occupancy grid marks empty is taken as zero, as the renderer does, so the
    mesh shows the NeRF that renders and not the haze left where no ray constrains it.
    """
    device = params["tables"].device
    box = grid.tight_box()
    if box is None:
        return trimesh.Trimesh()
    field_density = unit_density_fn(params, field_cfg, device)

    def rendered_density(points: torch.Tensor) -> torch.Tensor:
        return field_density(points) * grid.lookup(points)

    return extract_mesh(
        rendered_density,
        box[0],
        box[1],
        resolution=resolution,
        color_fn=color_fn_for(params, field_cfg, device),
    )


def evaluate_field(
    params: FieldParams,
    field_cfg: FieldConfig,
    grid: OccupancyGrid,
    test_views,
    cfg: RenderConfig,
    *,
    mesh_resolution: int = 128,
) -> tuple[dict, torch.Tensor, trimesh.Trimesh]:
    """Metrics on held-out views plus the mesh; returns ``(metrics, renders, mesh)``."""
    renders, ms = render_views(params, field_cfg, test_views, cfg, grid)
    target = composite_over(test_views.images.to(renders.device), cfg.background)
    per_view = [psnr(r, t) for r, t in zip(renders, target)]
    mesh = field_mesh(params, field_cfg, grid, mesh_resolution)
    metrics = {
        "psnr": sum(per_view) / len(per_view),
        "psnr_per_view": per_view,
        "ssim": ssim(renders, target),
        "render_ms": ms,
        "mesh_vertices": len(mesh.vertices),
    }
    if test_views.mesh_path is not None:
        metrics["chamfer"] = mesh_chamfer(mesh, trimesh.load(test_views.mesh_path, force="mesh"))
    return metrics, renders, mesh
