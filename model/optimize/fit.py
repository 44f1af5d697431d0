"""Per-object NeRF fit (InstantNGP-style): the reference the hypernetwork is compared against.

One object's field parameters (hash tables and MLP weights, same architecture the hypernetwork
emits) are optimised directly with Adam on random rays of its training views, through the shared
photometric step (``model.optimize.step``). Empty space is found from the field's own density by a
maintained occupancy grid (``model.nerf.occupancy.MaintainedGrid``: starts as every cell a
training view sees, refreshed every few steps); when the images have alpha and ``use_masks`` is
on, the grid starts from the visual hull carved from the masks instead, which makes the early
steps cheaper. Images without alpha are
trained against their own pixels.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from model.data.dataset import Views, validate_views
from model.nerf import config
from model.nerf.fields import Field, FieldConfig, FieldParams, world_density
from model.nerf.occupancy import MaintainedGrid, OccupancyConfig, OccupancyGrid, carve_from_masks, visible_cells
from model.nerf.provenance import source_digest
from model.nerf.rays import pixel_rays
from model.nerf.renderer import RenderConfig
from model.nerf.scene import SceneBox
from model.optimize.step import RayBatch, adam_with_decay, mse_to_psnr, photometric_loss

log = logging.getLogger(__name__)


@dataclass
class FitConfig:
    field: Field = dataclass_field(default_factory=FieldConfig)
    render: RenderConfig = dataclass_field(default_factory=lambda: RenderConfig(termination_threshold=0.0))
    occupancy: OccupancyConfig = dataclass_field(default_factory=OccupancyConfig)
    use_masks: bool = True
    steps: int = 1500
    rays_per_step: int = 4096
    lr: float = 1e-2
    final_lr_factor: float = 0.1
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 1e-6
    seed: int = 0


def fit_code_version() -> str:
    """Digest of the code a fit's result depends on (see ``model.nerf.provenance``)."""
    return source_digest("nerf", "optimize", "data/dataset.py")


@dataclass
class FitResult:
    params: FieldParams
    grid: OccupancyGrid
    scene: SceneBox
    history: list[dict] = dataclass_field(default_factory=list)
    wall_s: float = 0.0
    used_masks: bool = False


def training_rays(views: Views, device) -> RayBatch:
    """All pixels of the training views as rays, ``[P, 3]`` each, with RGBA targets ``[P, 4]``."""
    origins, directions = [], []
    for c2w, camera in zip(views.c2w, views.cameras):
        o, d = pixel_rays(c2w.to(device), camera)
        origins.append(o.reshape(-1, 3))
        directions.append(d.reshape(-1, 3))
    return RayBatch(torch.cat(origins), torch.cat(directions), views.images.to(device).reshape(-1, 4))


def initial_grid(views: Views, cfg: FitConfig, device) -> tuple[OccupancyGrid, bool]:
    """Where the field may hold matter from the start, and whether masks were used: the visual
    hull carved from the masks, or without masks the cells some training view sees."""
    c2w = views.c2w.to(device)
    if not (cfg.use_masks and views.has_alpha):
        seen = visible_cells(c2w, views.cameras, views.scene, cfg.occupancy.resolution)
        log.info("no masks: the training views see %.1f%% of the scene box; the grid grows from the field's density", 100 * seen.fraction)
        return seen, False
    masks = views.images[..., 3].to(device) > 0
    hull = carve_from_masks(c2w, masks, views.cameras, views.scene, resolution=cfg.occupancy.resolution)
    log.info("visual hull keeps %.1f%% of the scene box", 100 * hull.fraction)
    return hull, True


def fit_object(views: Views, cfg: FitConfig, *, device=None, progress: bool = True) -> FitResult:
    """Fit one object's field to its training ``views``."""
    validate_views(views.images, views.c2w)
    device = torch.device(device) if device is not None else torch.device("cpu")
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    scene = views.scene
    hull, used_masks = initial_grid(views, cfg, device)
    grid = MaintainedGrid(scene, cfg.occupancy, limit=hull, device=device)
    random_background = views.has_alpha
    if not random_background:
        log.info("the images have no alpha: training against their pixels over a %s background", cfg.render.background)

    params = {k: v.requires_grad_() for k, v in cfg.field.init_params(1, generator=generator, device=device).items()}
    tables = [v for k, v in params.items() if k == "tables"]
    weights = [v for k, v in params.items() if k != "tables"]
    groups = [{"params": tables, "weight_decay": 0.0}, {"params": weights, "weight_decay": cfg.weight_decay}]
    optimizer, scheduler = adam_with_decay([g for g in groups if g["params"]], lr=cfg.lr, steps=cfg.steps, final_lr_factor=cfg.final_lr_factor, betas=cfg.betas)

    rays = training_rays(views, device)
    history: list[dict] = []
    start = time.perf_counter()
    bar = tqdm(range(cfg.steps), desc="fit", unit="step", disable=not progress)
    for step in bar:
        grid.step(step, world_density(params, cfg.field, scene))
        idx = torch.randint(0, len(rays), (cfg.rays_per_step,), device=device, generator=generator)
        batch = RayBatch(rays.origins[idx], rays.directions[idx], rays.rgba[idx])
        loss, out = photometric_loss(
            params, cfg.field, batch, cfg.render, scene=scene, grid=grid.grid, random_background=random_background, generator=generator
        )
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
                "train_psnr": mse_to_psnr(mse),
                "samples_per_ray": float(out["samples"]) / cfg.rays_per_step,
                "occupied": grid.grid.fraction,
                "elapsed_s": time.perf_counter() - start,
            }
            history.append(record)
            bar.set_postfix(psnr=f"{record['train_psnr']:.2f}", spr=f"{record['samples_per_ray']:.1f}")
    params = {k: v.detach() for k, v in params.items()}
    grid.update(world_density(params, cfg.field, scene))
    return FitResult(params=params, grid=grid.grid, scene=scene, history=history, wall_s=time.perf_counter() - start, used_masks=used_masks)


def save_fit(run_dir: Path, result: FitResult, cfg: FitConfig, extra: dict | None = None) -> None:
    """``field.safetensors`` (parameters and occupancy grid) plus ``config.json`` (the fit config,
    the scene box and the code version that made it)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    tensors = {f"params.{k}": v.contiguous().cpu() for k, v in result.params.items()}
    tensors.update({f"grid.{k}": v.contiguous().cpu() for k, v in result.grid.state_dict().items()})
    save_file(tensors, str(run_dir / "field.safetensors"))
    meta = {"fit": config.to_dict(cfg), "scene_box": result.scene.to_aabb(), "code_version": fit_code_version(), **(extra or {})}
    (run_dir / "config.json").write_text(json.dumps(meta, indent=2))


def load_fit(run_dir: Path, device=None) -> tuple[FieldParams, OccupancyGrid, SceneBox, FitConfig, dict]:
    """Read what ``save_fit`` wrote: parameters, occupancy grid, scene box, config and the rest of the metadata."""
    run_dir = Path(run_dir)
    if not (run_dir / "field.safetensors").is_file():
        raise FileNotFoundError(f"{run_dir} holds no fitted field (field.safetensors); run `hypnerf fit` first")
    meta = json.loads((run_dir / "config.json").read_text())
    cfg = config.from_dict(FitConfig, meta.pop("fit"))
    scene = SceneBox.from_aabb(meta.pop("scene_box"))
    tensors = load_file(str(run_dir / "field.safetensors"), device=str(device or "cpu"))
    params = {k.removeprefix("params."): v for k, v in tensors.items() if k.startswith("params.")}
    grid = OccupancyGrid.from_state_dict({k.removeprefix("grid."): v for k, v in tensors.items() if k.startswith("grid.")})
    return params, grid, scene, cfg, meta
