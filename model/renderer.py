"""Volume rendering of a functional NeRF field, spending work only where the object is.

* Alpha compositing is computed from the exclusive cumulative sum of ``sigma * delta`` (optical
  depth), so transmittance is ``exp(-tau)`` with no product of many ``(1 - alpha)`` terms and no
  ``log(0)``: finite for densities up to the field's cap, rays that miss the box (``delta = 0``) and
  samples of zero length.
* An occupancy grid gates the samples: the field is evaluated only in occupied cells, and rays are
  marched through the grid's tight box instead of the whole scene box.
* Early ray termination: samples are evaluated in segments along the ray and a ray stops once its
  transmittance falls below a threshold.
* Colour is evaluated only for samples whose compositing weight matters.
* Images are rendered in chunks of rays, so memory stays bounded at any resolution.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from model.field import FieldConfig, FieldParams
from model.occupancy import OccupancyGrid
from model.rays import pixel_rays, ray_box_intersection
from model.sampler import stratified_distances

SCENE_BOX = ((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))


@dataclass
class RenderConfig:
    """How rays are sampled and which shortcuts are on.

    ``samples_per_ray`` stratified samples span each ray's entry and exit of the marched box (the
    grid's tight box when ``use_occupancy``, else the scene box). ``termination_threshold = 0``
    disables early termination; ``color_weight_threshold = 0`` evaluates colour at every sample.
    """

    samples_per_ray: int = 128
    use_occupancy: bool = True
    termination_threshold: float = 1e-4
    color_weight_threshold: float = 1e-4
    march_segment: int = 32
    chunk_rays: int = 8192
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "RenderConfig":
        data = dict(data)
        if "background" in data:
            data["background"] = tuple(data["background"])
        return cls(**data)


DENSE = RenderConfig(use_occupancy=False, termination_threshold=0.0, color_weight_threshold=0.0, march_segment=128)


def composite_weights(sigma_delta: torch.Tensor, optical_depth_before: torch.Tensor | None = None) -> torch.Tensor:
    """Compositing weights ``T_i * alpha_i`` from per-sample optical depth ``sigma_delta [R, S]``.

    ``optical_depth_before [R]`` is the optical depth already accumulated in front of the first
    sample (for marching in segments).
    """
    before = torch.cumsum(sigma_delta, dim=-1) - sigma_delta
    # The cumulative sum minus the sample itself is exact in the regime that matters (small depths);
    # where it loses digits the transmittance is exp(-large) = 0 anyway. Clamp guards the rounding.
    before = before.clamp_min(0.0)
    if optical_depth_before is not None:
        before = before + optical_depth_before[:, None]
    alpha = -torch.expm1(-sigma_delta)
    return torch.exp(-before) * alpha


def _to_unit(points: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor) -> torch.Tensor:
    return ((points - box_min) / (box_max - box_min)).clamp(0.0, 1.0)


def render_rays(
    params: FieldParams,
    field_cfg: FieldConfig,
    origins: torch.Tensor,
    directions: torch.Tensor,
    cfg: RenderConfig,
    *,
    grid: OccupancyGrid | None = None,
    background: torch.Tensor | None = None,
    jitter: bool = False,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """Render rays ``[R, 3]`` of one object (``params`` with batch 1); differentiable.

    Returns ``rgb [R, 3]`` (composited over ``background``, ``[3]`` or ``[R, 3]``), ``opacity [R]``,
    ``depth [R]`` (expected distance of the visible surface, weighted) and ``samples`` (density
    evaluations made, a 0-d tensor).
    """
    device = origins.device
    scene_min = torch.tensor(SCENE_BOX[0], device=device)
    scene_max = torch.tensor(SCENE_BOX[1], device=device)
    if background is None:
        background = torch.tensor(cfg.background, device=device)
    rays = origins.shape[0]

    box = grid.tight_box() if (cfg.use_occupancy and grid is not None) else (scene_min, scene_max)
    rgb = torch.zeros(rays, 3, device=device)
    opacity = torch.zeros(rays, device=device)
    depth = torch.zeros(rays, device=device)
    evaluated = torch.zeros((), dtype=torch.long, device=device)
    if box is None:  # the grid says the object is empty
        return {"rgb": rgb + background, "opacity": opacity, "depth": depth, "samples": evaluated}

    near, far, hit = ray_box_intersection(origins, directions, box[0], box[1])
    far = torch.where(hit, far, near)
    delta = (far - near).clamp_min(0.0) / cfg.samples_per_ray
    skip_empty = cfg.use_occupancy and grid is not None

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
        sigma, geo = field_cfg.density(params, _to_unit(points[live_idx, col_idx], scene_min, scene_max)[None])
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
        opacity = opacity.index_add(0, live, weights.sum(dim=-1))
        tau = tau.index_add(0, live, sd.sum(dim=-1))
        if cfg.termination_threshold > 0:
            live = live[torch.exp(-tau[live]) > cfg.termination_threshold]

    rgb = rgb + (1.0 - opacity)[:, None] * background
    return {"rgb": rgb, "opacity": opacity, "depth": depth, "samples": evaluated}


@torch.no_grad()
def render_image(
    params: FieldParams,
    field_cfg: FieldConfig,
    c2w: torch.Tensor,
    width: int,
    height: int,
    focal: float,
    cfg: RenderConfig,
    *,
    grid: OccupancyGrid | None = None,
) -> dict[str, torch.Tensor]:
    """Render one view in chunks of ``cfg.chunk_rays`` rays; returns ``rgb [H, W, 3]``,
    ``opacity [H, W]``, ``depth [H, W]`` and ``samples`` (total density evaluations)."""
    if c2w.shape != (4, 4) or not bool(torch.isfinite(c2w).all()):
        raise ValueError("the camera pose must be a finite 4x4 camera-to-world matrix (it has NaN/Inf or the wrong shape)")
    if width < 1 or height < 1 or not focal > 0 or not torch.isfinite(torch.tensor(focal)):
        raise ValueError(f"image size must be positive and focal finite and positive, got {width}x{height}, focal {focal}")
    origins, directions = pixel_rays(c2w.float(), width, height, focal)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    parts: dict[str, list[torch.Tensor]] = {"rgb": [], "opacity": [], "depth": []}
    samples = 0
    for start in range(0, origins.shape[0], cfg.chunk_rays):
        out = render_rays(
            params, field_cfg, origins[start : start + cfg.chunk_rays], directions[start : start + cfg.chunk_rays], cfg, grid=grid
        )
        for key in parts:
            parts[key].append(out[key])
        samples += int(out["samples"])
    return {
        "rgb": torch.cat(parts["rgb"]).reshape(height, width, 3),
        "opacity": torch.cat(parts["opacity"]).reshape(height, width),
        "depth": torch.cat(parts["depth"]).reshape(height, width),
        "samples": torch.tensor(samples),
    }
