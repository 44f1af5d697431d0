"""Volume rendering of a functional NeRF field, spending work only where the object is.

* Alpha compositing is computed from the exclusive cumulative sum of ``sigma * delta`` (optical
  depth in front of each sample), so transmittance is ``exp(-tau)`` with no product of many
  ``(1 - alpha)`` terms, no ``log(0)`` and no cancellation when one sample's depth is huge: finite
  for densities up to the field's cap, rays that miss the box (``delta = 0``) and zero-length samples.
* Steps are measured in the unit cube of the scene box (``model.nerf.scene``), the space the
  field's densities live in, so a scene renders the same at any world scale.
* An occupancy grid gates the samples: the field is evaluated only in occupied cells
  (``skip_empty``), and rays are marched through the grid's tight box instead of the whole scene
  box (``tight_box``).
* Early ray termination: samples are evaluated in segments along the ray and a ray stops once its
  transmittance falls below a threshold.
* Colour is evaluated only for samples whose compositing weight matters; a skipped sample's weight
  goes to the background (it neither keeps its weight nor renders black).
* Images are rendered in chunks of rays, so memory stays bounded at any resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from model.nerf.fields import Field, FieldParams
from model.nerf.occupancy import OccupancyGrid
from model.nerf.rays import Intrinsics, pixel_rays, ray_box_intersection
from model.nerf.sampler import stratified_distances
from model.nerf.scene import SceneBox


@dataclass
class RenderConfig:
    """How rays are sampled and which shortcuts are on.

    ``samples_per_ray`` stratified samples span each ray's entry and exit of the marched box: the
    grid's tight box when ``tight_box`` (and a grid is given), else the scene box. ``skip_empty``
    evaluates the field only in occupied cells; without it every sample is evaluated and the
    grid, part of the model, zeroes the density of empty cells. ``termination_threshold = 0``
    disables early termination; ``color_weight_threshold = 0`` evaluates colour at every sample.
    """

    samples_per_ray: int = 128
    tight_box: bool = True
    skip_empty: bool = True
    termination_threshold: float = 1e-4
    color_weight_threshold: float = 1e-4
    march_segment: int = 32
    chunk_rays: int = 8192
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)


DENSE = RenderConfig(tight_box=False, skip_empty=False, termination_threshold=0.0, color_weight_threshold=0.0, march_segment=128)
"""The reference renderer: samples over the whole scene box, every one evaluated, no shortcuts."""
DENSE_TIGHT = replace(DENSE, tight_box=True)
"""The reference renderer marching the grid's tight box (finer steps, still every sample evaluated)."""


def composite_weights(sigma_delta: torch.Tensor, optical_depth_before: torch.Tensor | None = None) -> torch.Tensor:
    """Compositing weights ``T_i * alpha_i`` from per-sample optical depth ``sigma_delta [R, S]``.

    ``optical_depth_before [R]`` is the optical depth already accumulated in front of the first
    sample (for marching in segments).
    """
    # exclusive cumulative sum: the depth strictly in front of each sample, with no cancellation
    before = torch.cumsum(F.pad(sigma_delta[:, :-1], (1, 0)), dim=-1)
    if optical_depth_before is not None:
        before = before + optical_depth_before[:, None]
    alpha = -torch.expm1(-sigma_delta)
    return torch.exp(-before) * alpha


def render_rays(
    params: FieldParams,
    field_cfg: Field,
    origins: torch.Tensor,
    directions: torch.Tensor,
    cfg: RenderConfig,
    *,
    scene: SceneBox,
    grid: OccupancyGrid | None = None,
    background: torch.Tensor | None = None,
    jitter: bool = False,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """Render world rays ``[R, 3]`` of one object (``params`` with batch 1) in ``scene``; differentiable.

    Returns ``rgb [R, 3]`` (composited over ``background``, ``[3]`` or ``[R, 3]``), ``opacity [R]``
    (the weight of the samples that were shaded), ``depth [R]`` (expected distance of the visible
    surface, weighted) and ``samples`` (density evaluations made, a 0-d tensor).
    """
    device = origins.device
    scene_min, scene_max = scene.tensors(device)
    if background is None:
        background = torch.tensor(cfg.background, device=device)
    rays = origins.shape[0]

    box = grid.tight_box() if (cfg.tight_box and grid is not None) else (scene_min, scene_max)
    rgb = torch.zeros(rays, 3, device=device)
    opacity = torch.zeros(rays, device=device)
    depth = torch.zeros(rays, device=device)
    evaluated = torch.zeros((), dtype=torch.long, device=device)
    if box is None:  # the grid says the object is empty
        return {"rgb": rgb + background, "opacity": opacity, "depth": depth, "samples": evaluated}

    near, far, hit = ray_box_intersection(origins, directions, box[0], box[1])
    far = torch.where(hit, far, near)
    # step length in the unit cube, where the field's densities live
    delta = (far - near).clamp_min(0.0) / cfg.samples_per_ray * scene.unit_lengths(directions)
    skip_empty = cfg.skip_empty and grid is not None

    view = field_cfg.view_term(params, directions)[0]
    segment = cfg.march_segment if cfg.termination_threshold > 0 else cfg.samples_per_ray
    tau = torch.zeros(rays, device=device)  # optical depth accumulated so far
    live = hit.nonzero().squeeze(1)  # rays still marching
    for start in range(0, cfg.samples_per_ray, segment):
        if live.numel() == 0:
            break
        stop = min(start + segment, cfg.samples_per_ray)
        t_seg, _ = stratified_distances(
            near[live], far[live], cfg.samples_per_ray, start=start, stop=stop, jitter=jitter, generator=generator
        )
        points = origins[live, None] + directions[live, None] * t_seg[..., None]  # [A, s, 3]
        occupied = grid.lookup(points) if grid is not None else None
        if skip_empty:
            live_idx, col_idx = occupied.nonzero(as_tuple=True)
        else:
            live_idx, col_idx = torch.ones_like(t_seg, dtype=torch.bool).nonzero(as_tuple=True)
        if live_idx.numel() == 0:
            continue
        ts = t_seg[live_idx, col_idx]
        sigma, geo = field_cfg.density(params, scene.to_unit(points[live_idx, col_idx])[None])
        sigma, geo = sigma[0].float(), geo[0]
        if occupied is not None and not skip_empty:
            # the grid is part of the model: empty cells hold no density even when evaluated
            sigma = sigma * occupied[live_idx, col_idx]
        evaluated = evaluated + live_idx.numel()

        sd = torch.zeros_like(t_seg).index_put((live_idx, col_idx), sigma * delta[live][live_idx])
        weights = composite_weights(sd, tau[live])
        w = weights[live_idx, col_idx]
        keep = w > cfg.color_weight_threshold if cfg.color_weight_threshold > 0 else torch.ones_like(w, dtype=torch.bool)
        if bool(keep.any()):
            rows = live[live_idx[keep]]
            col = field_cfg.color_from_view_term(params, geo[keep][None], view[rows][None])[0].float()
            wk = w[keep]
            rgb = rgb.index_add(0, rows, wk[:, None] * col)
            depth = depth.index_add(0, rows, wk * ts[keep])
            opacity = opacity.index_add(0, rows, wk)
        tau = tau.index_add(0, live, sd.sum(dim=-1))
        if cfg.termination_threshold > 0:
            live = live[torch.exp(-tau[live]) > cfg.termination_threshold]

    rgb = rgb + (1.0 - opacity)[:, None] * background
    return {"rgb": rgb, "opacity": opacity, "depth": depth, "samples": evaluated}


@torch.no_grad()
def render_image(
    params: FieldParams,
    field_cfg: Field,
    c2w: torch.Tensor,
    camera: Intrinsics,
    cfg: RenderConfig,
    *,
    scene: SceneBox,
    grid: OccupancyGrid | None = None,
) -> dict[str, torch.Tensor]:
    """Render one view in chunks of ``cfg.chunk_rays`` rays; returns ``rgb [H, W, 3]``,
    ``opacity [H, W]``, ``depth [H, W]`` and ``samples`` (total density evaluations)."""
    if c2w.shape != (4, 4) or not bool(torch.isfinite(c2w).all()):
        raise ValueError("the camera pose must be a finite 4x4 camera-to-world matrix (it has NaN/Inf or the wrong shape)")
    origins, directions = pixel_rays(c2w.float(), camera)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    parts: dict[str, list[torch.Tensor]] = {"rgb": [], "opacity": [], "depth": []}
    samples = 0
    for start in range(0, origins.shape[0], cfg.chunk_rays):
        stop = start + cfg.chunk_rays
        out = render_rays(params, field_cfg, origins[start:stop], directions[start:stop], cfg, scene=scene, grid=grid)
        for key in parts:
            parts[key].append(out[key])
        samples += int(out["samples"])
    height, width = camera.height, camera.width
    return {
        "rgb": torch.cat(parts["rgb"]).reshape(height, width, 3),
        "opacity": torch.cat(parts["opacity"]).reshape(height, width),
        "depth": torch.cat(parts["depth"]).reshape(height, width),
        "samples": torch.tensor(samples),
    }
