"""Quality of a fitted (or generated) NeRF: held-out renders, PSNR/SSIM, mesh and Chamfer distance."""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import torch
import trimesh

from model.field import FieldConfig, FieldParams
from model.fit import scene_box, unit_density_fn
from model.mesh import extract_mesh
from model.metrics import mesh_chamfer, psnr, ssim
from model.occupancy import OccupancyGrid
from model.renderer import RenderConfig, render_image

log = logging.getLogger(__name__)


def composite_over(rgba: torch.Tensor, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """Straight-alpha RGBA ``[..., 4]`` over a constant background -> RGB ``[..., 3]``."""
    bg = torch.tensor(background, dtype=rgba.dtype, device=rgba.device)
    return rgba[..., :3] * rgba[..., 3:] + bg * (1 - rgba[..., 3:])


def render_views(params: FieldParams, field_cfg: FieldConfig, views, cfg: RenderConfig, grid: OccupancyGrid | None):
    """Render every view of ``views``; returns images ``[V, H, W, 3]``, the median ms per image
    and the mean density evaluations per ray."""
    images, times, samples = [], [], 0
    for c2w in views.c2w:
        start = time.perf_counter()
        out = render_image(params, field_cfg, c2w, views.width, views.height, views.focal, cfg, grid=grid)
        times.append(1000 * (time.perf_counter() - start))
        images.append(out["rgb"])
        samples += int(out["samples"])
    per_ray = samples / (len(images) * views.width * views.height)
    return torch.stack(images), float(torch.tensor(times).median()), per_ray


def color_fn_for(params: FieldParams, field_cfg: FieldConfig, device):
    """Vertex colours: the colour net seen from straight above (the field's view dependence is weak)."""
    lo, hi = scene_box(device)

    def fn(points: torch.Tensor) -> torch.Tensor:
        unit = ((points - lo) / (hi - lo)).clamp(0, 1)[None]
        _, geo = field_cfg.density(params, unit)
        down = torch.tensor([0.0, 0.0, -1.0], device=points.device).expand_as(points)[None]
        return field_cfg.color_from_view_term(params, geo, field_cfg.view_term(params, down))[0]

    return fn


def field_mesh(params: FieldParams, field_cfg: FieldConfig, grid: OccupancyGrid, resolution: int = 128) -> trimesh.Trimesh:
    """Marching-cubes mesh of the field over its occupied box, with vertex colours.

    Density in cells the occupancy grid marks empty is taken as zero, as the renderer does, so the
    mesh shows the NeRF that renders and not the haze left where no ray constrains it.
    """
    device = next(iter(params.values())).device
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
    renders, ms, samples_per_ray = render_views(params, field_cfg, test_views, cfg, grid)
    target = composite_over(test_views.images.to(renders.device), cfg.background)
    per_view = [psnr(r, t) for r, t in zip(renders, target)]
    mesh = field_mesh(params, field_cfg, grid, mesh_resolution)
    metrics = {
        "psnr": sum(per_view) / len(per_view),
        "psnr_per_view": per_view,
        "ssim": ssim(renders, target),
        "render_ms": ms,
        "samples_per_ray": samples_per_ray,
        "mesh_vertices": len(mesh.vertices),
    }
    if test_views.mesh_path is not None:
        metrics["chamfer"] = mesh_chamfer(mesh, trimesh.load(test_views.mesh_path, force="mesh"))
    return metrics, renders, mesh


def fit_and_evaluate(root: Path, object_id: str, out: Path, cfg, device, mesh_resolution: int = 128) -> dict:
    """``hypnerf fit``: fit one object, evaluate it on its held-out views, and write the checkpoint,
    renders, mesh, history and ``metrics.json`` into ``out``; returns the metrics."""
    from model.data.dataset import load_views
    from model.fit import fit_object, save_fit
    from model.images import save_png
    from model.mesh import export_mesh

    root, out = Path(root), Path(out)
    train = load_views(root / object_id, split="train")
    test = load_views(root / object_id, split="test")
    log.info("fitting %s (%d training views, %dx%d) on %s", object_id, len(train.c2w), train.width, train.height, device)
    result = fit_object(train, cfg, device=device)
    save_fit(out, result, cfg, {"data": str(root.resolve()), "object": object_id})
    log.info("evaluating on %d held-out views", len(test.c2w))
    metrics, renders, mesh = evaluate_field(result.params, cfg.field, result.grid, test, RenderConfig(), mesh_resolution=mesh_resolution)
    if not math.isfinite(metrics.get("chamfer", 0.0)):
        log.warning("the fitted field has no surface above the mesh threshold; chamfer is reported as null")
        metrics["chamfer"] = None
    metrics.update({"wall_s": result.wall_s, "object": object_id, "steps": cfg.steps, "occupied_fraction": result.grid.fraction})
    (out / "renders").mkdir(exist_ok=True)
    for i, image in enumerate(renders):
        save_png(out / "renders" / f"test_{i:03d}.png", image)
    export_mesh(mesh, out / "mesh.glb")
    (out / "history.json").write_text(json.dumps(result.history, indent=2))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    chamfer = f"{metrics['chamfer']:.4f}" if metrics.get("chamfer") is not None else "n/a"
    log.info("%s: PSNR %.2f dB, SSIM %.4f, Chamfer %s, fit %.1f s -> %s", object_id, metrics["psnr"], metrics["ssim"], chamfer, result.wall_s, out)
    return metrics
