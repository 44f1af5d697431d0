"""Quality of a fitted (or generated) NeRF: held-out renders, PSNR (full image and foreground, beside
the blank-image floor), SSIM, mesh and Chamfer distance."""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import torch
import trimesh

from model.data.dataset import Views, load_views
from model.eval.metrics import image_quality, mesh_chamfer, ssim
from model.nerf.fields import Field, FieldParams
from model.nerf.images import composite_over, save_png
from model.nerf.mesh import export_mesh, field_mesh
from model.nerf.occupancy import OccupancyGrid
from model.nerf.provenance import source_digest
from model.nerf.renderer import RenderConfig, render_image
from model.nerf.scene import SceneBox
from model.optimize.fit import FitConfig, fit_object, save_fit

log = logging.getLogger(__name__)


def evaluation_code_version() -> str:
    """Digest of the code a fit's ``metrics.json`` depends on: the fit's and the evaluation's."""
    return source_digest("nerf", "optimize", "data/dataset.py", "eval/field.py", "eval/metrics.py")


def render_views(params: FieldParams, field_cfg: Field, views: Views, cfg: RenderConfig, grid: OccupancyGrid | None, scene: SceneBox | None = None):
    """Render every view of ``views``; returns images ``[V, H, W, 3]``, opacities ``[V, H, W]``,
    the median ms per image and the mean density evaluations per ray."""
    scene = scene or views.scene
    images, opacity, times, samples = [], [], [], 0
    for c2w, camera in zip(views.c2w, views.cameras):
        start = time.perf_counter()
        out = render_image(params, field_cfg, c2w, camera, cfg, scene=scene, grid=grid)
        times.append(1000 * (time.perf_counter() - start))
        images.append(out["rgb"])
        opacity.append(out["opacity"])
        samples += int(out["samples"])
    per_ray = samples / (len(images) * views.width * views.height)
    return torch.stack(images), torch.stack(opacity), float(torch.tensor(times).median()), per_ray


def evaluate_field(
    params: FieldParams,
    field_cfg: Field,
    grid: OccupancyGrid,
    test_views: Views,
    cfg: RenderConfig,
    *,
    scene: SceneBox | None = None,
    mesh_resolution: int = 128,
) -> tuple[dict, torch.Tensor, trimesh.Trimesh]:
    """Metrics on held-out views plus the mesh; returns ``(metrics, renders, mesh)``.

    ``psnr`` is over the full image, ``psnr_fg`` over the foreground (see
    ``model.eval.metrics.image_quality``), ``floor_psnr`` / ``floor_psnr_fg`` the same for a blank
    background image; Chamfer distance is in scene-box units.
    """
    scene = scene or test_views.scene
    renders, opacity, ms, samples_per_ray = render_views(params, field_cfg, test_views, cfg, grid, scene)
    quality = image_quality(renders, test_views.images.to(renders.device), opacity, cfg.background)
    target = composite_over(test_views.images.to(renders.device), cfg.background)
    mesh = field_mesh(params, field_cfg, grid, scene, mesh_resolution)
    metrics = {
        **quality,
        "ssim": ssim(renders, target),
        "render_ms": ms,
        "samples_per_ray": samples_per_ray,
        "mesh_vertices": len(mesh.vertices),
    }
    if test_views.mesh_path is not None:
        metrics["chamfer"] = mesh_chamfer(mesh, trimesh.load(test_views.mesh_path, force="mesh"), unit=scene.longest_side)
    return metrics, renders, mesh


def fit_and_evaluate(root: Path, object_id: str, out: Path, cfg: FitConfig, device, mesh_resolution: int = 128) -> dict:
    """``hypnerf fit``: fit one object, evaluate it on its held-out views, and write the checkpoint,
    renders, mesh, history and ``metrics.json`` into ``out``; returns the metrics."""
    root, out = Path(root), Path(out)
    train = load_views(root / object_id, split="train")
    test = load_views(root / object_id, split="test")
    log.info("fitting %s (%d training views, %dx%d, scene box %s) on %s", object_id, len(train.c2w), train.width, train.height, train.scene.to_aabb(), device)
    result = fit_object(train, cfg, device=device)
    save_fit(out, result, cfg, {"data": str(root.resolve()), "object": object_id})
    log.info("evaluating on %d held-out views", len(test.c2w))
    metrics, renders, mesh = evaluate_field(result.params, cfg.field, result.grid, test, RenderConfig(), mesh_resolution=mesh_resolution)
    if not math.isfinite(metrics.get("chamfer", 0.0)):
        log.warning("the fitted field has no surface above the mesh threshold; chamfer is reported as null")
        metrics["chamfer"] = None
    metrics.update(
        {
            "wall_s": result.wall_s, "object": object_id, "steps": cfg.steps, "occupied_fraction": result.grid.fraction,
            "used_masks": result.used_masks, "trained_with_alpha": train.has_alpha, "code_version": evaluation_code_version(),
        }
    )
    (out / "renders").mkdir(exist_ok=True)
    for i, image in enumerate(renders):
        save_png(out / "renders" / f"test_{i:03d}.png", image)
    export_mesh(mesh, out / "mesh.glb")
    (out / "history.json").write_text(json.dumps(result.history, indent=2))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    chamfer = f"{metrics['chamfer']:.4f}" if metrics.get("chamfer") is not None else "n/a"
    fg = f"{metrics['psnr_fg']:.2f}" if metrics["psnr_fg"] is not None else "n/a"
    log.info(
        "%s: PSNR %.2f dB (floor %.2f), foreground %s dB (floor %.2f), SSIM %.4f, Chamfer %s, fit %.1f s -> %s",
        object_id, metrics["psnr"], metrics["floor_psnr"], fg, metrics["floor_psnr_fg"] or float("nan"), metrics["ssim"], chamfer, result.wall_s, out,
    )
    return metrics
