"""Per-object NeRF fit (InstantNGP-style): the reference the hypernetwork is compared against.

One object's field parameters (hash tables and MLP weights, same architecture the hypernetwork
emits) are optimised directly with Adam on random rays of its training views. Empty space is
skipped from the first step by a visual hull carved from the training masks; the hull is then
narrowed by the field's own density as training goes (a maintained occupancy grid, as in
InstantNGP). Training composites over a random background per ray so that opacity is learned.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from model.data.dataset import validate_views
from model.field import FieldConfig, FieldParams
from model.fields import field_config_from_dict
from model.occupancy import OccupancyGrid, carve_from_masks, density_threshold, dilate, max_cell_density
from model.rays import pixel_rays
from model.renderer import SCENE_BOX, RenderConfig, render_rays

log = logging.getLogger(__name__)


@dataclass
class FitConfig:
    field: FieldConfig = dataclass_field(default_factory=FieldConfig)
    render: RenderConfig = dataclass_field(default_factory=lambda: RenderConfig(termination_threshold=0.0))
    steps: int = 1500
    rays_per_step: int = 4096
    lr: float = 1e-2
    final_lr_factor: float = 0.1
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 1e-6
    grid_resolution: int = 64
    grid_update_every: int = 16
    grid_warmup_steps: int = 64
    grid_decay: float = 0.95
    grid_cell_opacity: float = 2e-3
    seed: int = 0

    def to_dict(self) -> dict:
        out = asdict(self)
        out["field"] = self.field.to_dict()
        out["render"] = self.render.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "FitConfig":
        data = dict(data)
        data["field"] = field_config_from_dict(data.get("field", {}))
        data["render"] = RenderConfig.from_dict(data.get("render", {}))
        if "betas" in data:
            data["betas"] = tuple(data["betas"])
        return cls(**data)


@dataclass
class FitResult:
    params: FieldParams
    grid: OccupancyGrid
    history: list[dict] = dataclass_field(default_factory=list)
    wall_s: float = 0.0


def scene_box(device) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor(SCENE_BOX[0], device=device), torch.tensor(SCENE_BOX[1], device=device)


def unit_density_fn(params: FieldParams, field_cfg: FieldConfig, device):
    """``points [N, 3]`` in world coordinates -> density ``[N]``, for grids and meshes."""
    lo, hi = scene_box(device)

    def fn(points: torch.Tensor) -> torch.Tensor:
        unit = ((points - lo) / (hi - lo)).clamp(0, 1)
        return field_cfg.density(params, unit[None])[0][0]

    return fn


class _MaintainedGrid:
    """Occupancy during training: the carved hull, narrowed by a decaying max of the field's density."""

    def __init__(self, hull: OccupancyGrid, cfg: FitConfig):
        self.hull = hull
        self.cfg = cfg
        self.cell_density = torch.full(hull.occupied.shape, float("inf"), device=hull.occupied.device)
        self.threshold = density_threshold(cfg.grid_resolution, hull.box_min, hull.box_max, cfg.grid_cell_opacity)
        self.grid = hull

    @torch.no_grad()
    def update(self, density_fn, generator: torch.Generator) -> None:
        fresh = max_cell_density(
            density_fn,
            self.cfg.grid_resolution,
            self.hull.box_min,
            self.hull.box_max,
            cells=self.hull.occupied,  # cells outside the hull stay empty whatever their density
            samples_per_cell=1,
            generator=generator,
        )
        decayed = torch.where(torch.isinf(self.cell_density), fresh, self.cell_density * self.cfg.grid_decay)
        self.cell_density = torch.maximum(decayed, fresh)
        occupied = self.hull.occupied & dilate(self.cell_density > self.threshold, 1)
        self.grid = OccupancyGrid(occupied, self.hull.box_min, self.hull.box_max)


def training_rays(views, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """All pixels of the training views as rays: origins, directions ``[P, 3]`` and RGBA ``[P, 4]``."""
    origins, directions = pixel_rays(views.c2w.to(device), views.width, views.height, views.focal)
    return origins.reshape(-1, 3), directions.reshape(-1, 3), views.images.to(device).reshape(-1, 4)


def fit_object(views, cfg: FitConfig, *, device=None, progress: bool = True) -> FitResult:
    """Fit one object's field to its training ``views`` (a ``model.data.dataset.Views``)."""
    validate_views(views.images, views.c2w)
    device = torch.device(device) if device is not None else torch.device("cpu")
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    lo, hi = scene_box(device)
    hull = carve_from_masks(
        views.c2w.to(device), views.images[..., 3].to(device) > 0, views.focal, lo, hi, resolution=cfg.grid_resolution
    )
    log.info("visual hull keeps %.1f%% of the scene box", 100 * hull.fraction)
    grid = _MaintainedGrid(hull, cfg)

    params = {k: v.requires_grad_() for k, v in cfg.field.init_params(1, generator=generator, device=device).items()}
    mlp = [v for k, v in params.items() if k != "tables"]
    optimizer = torch.optim.Adam(
        [{"params": [params["tables"]], "weight_decay": 0.0}, {"params": mlp, "weight_decay": cfg.weight_decay}],
        lr=cfg.lr,
        betas=cfg.betas,
        eps=1e-15,
    )
    decay = math.log(cfg.final_lr_factor) / max(cfg.steps, 1)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: math.exp(decay * step))

    origins, directions, rgba = training_rays(views, device)
    history: list[dict] = []
    start = time.perf_counter()
    bar = tqdm(range(cfg.steps), desc="fit", unit="step", disable=not progress)
    for step in bar:
        if step >= cfg.grid_warmup_steps and step % cfg.grid_update_every == 0:
            grid.update(unit_density_fn(params, cfg.field, device), generator)
        idx = torch.randint(0, origins.shape[0], (cfg.rays_per_step,), device=device, generator=generator)
        background = torch.rand(cfg.rays_per_step, 3, device=device, generator=generator)
        target = rgba[idx, :3] * rgba[idx, 3:] + background * (1 - rgba[idx, 3:])
        out = render_rays(
            params, cfg.field, origins[idx], directions[idx], cfg.render, grid=grid.grid, background=background, jitter=True, generator=generator
        )
        loss = torch.mean((out["rgb"] - target) ** 2)
        if loss.requires_grad:  # a batch whose rays all miss the occupied box has nothing to train
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        scheduler.step()
        if step % 50 == 0 or step == cfg.steps - 1:
            mse = loss.item()
            record = {
                "step": step,
                "loss": mse,
                "train_psnr": -10 * math.log10(max(mse, 1e-10)),
                "samples_per_ray": float(out["samples"]) / cfg.rays_per_step,
                "occupied": grid.grid.fraction,
                "elapsed_s": time.perf_counter() - start,
            }
            history.append(record)
            bar.set_postfix(psnr=f"{record['train_psnr']:.2f}", spr=f"{record['samples_per_ray']:.1f}")
    params = {k: v.detach() for k, v in params.items()}
    grid.update(unit_density_fn(params, cfg.field, device), generator)
    return FitResult(params=params, grid=grid.grid, history=history, wall_s=time.perf_counter() - start)


def save_fit(run_dir: Path, result: FitResult, cfg: FitConfig, extra: dict | None = None) -> None:
    """``field.safetensors`` (parameters and occupancy grid) plus ``config.json``."""
    run_dir.mkdir(parents=True, exist_ok=True)
    tensors = {f"params.{k}": v.contiguous().cpu() for k, v in result.params.items()}
    tensors.update({f"grid.{k}": v.contiguous().cpu() for k, v in result.grid.state_dict().items()})
    save_file(tensors, str(run_dir / "field.safetensors"))
    (run_dir / "config.json").write_text(json.dumps({"fit": cfg.to_dict(), **(extra or {})}, indent=2))


def load_fit(run_dir: Path, device=None) -> tuple[FieldParams, OccupancyGrid, FitConfig, dict]:
    """Read what ``save_fit`` wrote: parameters, occupancy grid, config and the extra metadata."""
    run_dir = Path(run_dir)
    if not (run_dir / "field.safetensors").is_file():
        raise FileNotFoundError(f"{run_dir} holds no fitted field (field.safetensors); run `hypnerf fit` first")
    meta = json.loads((run_dir / "config.json").read_text())
    cfg = FitConfig.from_dict(meta.pop("fit"))
    tensors = load_file(str(run_dir / "field.safetensors"), device=str(device or "cpu"))
    params = {k.removeprefix("params."): v for k, v in tensors.items() if k.startswith("params.")}
    grid = OccupancyGrid.from_state_dict({k.removeprefix("grid."): v for k, v in tensors.items() if k.startswith("grid.")})
    return params, grid, cfg, meta
