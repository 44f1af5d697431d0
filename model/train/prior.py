"""Training the hypernetwork prior end to end through the renderer (paper section 3.1, step 1).

Each step draws several instances, runs the hypernetwork once for all of them, and renders a
share of the step's rays for each from its own training views, over a random background. Only
the learnable parts are the heads and the codebooks: the NeRFs are differentiable layers.

Modelling only what a scene needs: rays are marched only through each shape's visual hull
(carved from its masks, shared by its colour variants), so empty space costs no field evaluation.
Space outside the hull is never seen by a training ray, so a free-space loss pushes the density
of random points there to zero; the generated NeRFs then mark their own empty space and a grid
derived from their density (as the service builds one) matches the object.

Data parallel with ``torch.distributed``: ``torchrun --nproc_per_node=2 -m model.cli train ...`` runs
one process per core (gloo on CPU, NCCL on GPUs), each rendering different instances; gradients
are averaged by ``DistributedDataParallel``. Randomness of a step depends only on (seed, step,
rank), so a resumed run continues exactly as an uninterrupted one would.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.distributed as dist
from tqdm import tqdm

from model.data.category import CategoryData, free_space_grids, free_space_points, grid_of, load_category, shape_grids
from model.data.dataset import load_views
from model.eval.metrics import image_quality
from model.nerf import config
from model.nerf.device import default_device
from model.nerf.fields import FieldParams
from model.nerf.fields.hashgrid import select
from model.nerf.renderer import RenderConfig, render_image
from model.optimize.step import RayBatch, adam_with_decay, mse_to_psnr, photometric_loss
from model.prior.codes import generated_grid
from model.prior.hypernet import HyperNetConfig, HyperNetwork, code_penalty
from model.prior.io import export_prior

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"


@dataclass
class TrainConfig:
    steps: int = 20000
    objects_per_step: int = 4
    rays_per_step: int = 4096
    lr: float = 1e-3
    final_lr_factor: float = 0.1
    betas: tuple[float, float] = (0.9, 0.99)
    grad_clip: float = 1.0
    code_penalty: float = 1e-4
    # A variational codebook with a fixed posterior width: each drawn code is perturbed by Gaussian
    # noise of this many times its codebook's per-dimension std, so that neighbourhoods of the
    # codes decode to valid NeRFs (with the width fixed, the KL term reduces to the code penalty).
    code_noise: float = 0.0
    free_space_weight: float = 0.1
    free_space_points: int = 1024
    grid_resolution: int = 64
    occupancy: str = "hull"  # training occupancy: hull, mesh or box (model.data.category.shape_grids)
    render: RenderConfig = field(default_factory=lambda: RenderConfig(termination_threshold=0.0))
    validate_every: int = 500
    validation_instances: int = 4
    checkpoint_every: int = 500
    log_every: int = 50
    seed: int = 0


# ---------------------------------------------------------------------------------------------
# Distributed helpers


@dataclass
class Workers:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0


def start_workers() -> Workers:
    """Join the process group torchrun describes in the environment (a single worker without it)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Workers(device=default_device())
    if torch.cuda.is_available():
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        dist.init_process_group("nccl")
        return Workers(dist.get_rank(), world, torch.device("cuda", local))
    dist.init_process_group("gloo")
    return Workers(dist.get_rank(), world, torch.device("cpu"))


def _step_generator(seed: int, step: int, rank: int, device) -> torch.Generator:
    return torch.Generator(device=device).manual_seed(((seed * 1_000_003 + step) * 1009 + rank) % (2**63))


def step_instances(instances: int, per_worker: int, seed: int, step: int, workers: Workers) -> list[int]:
    """The instances one worker trains on at ``step``: distinct across workers, each step a fresh draw."""
    order = torch.randperm(instances, generator=torch.Generator().manual_seed(seed * 7919 + step))
    total = min(instances, per_worker * workers.world)
    mine = order[:total].tensor_split(workers.world)[workers.rank]
    return mine.tolist() if mine.numel() else order[: min(per_worker, instances)].tolist()


# ---------------------------------------------------------------------------------------------
# One step


def instance_loss(
    params: FieldParams,
    data: CategoryData,
    instance: int,
    occupied: torch.Tensor,
    free_grid: torch.Tensor,
    rays: int,
    directions_cam: torch.Tensor,
    cfg: TrainConfig,
    field_cfg,
    generator: torch.Generator,
) -> tuple[torch.Tensor, dict]:
    """Photometric loss on ``rays`` random training pixels of one instance, plus the free-space term."""
    device = directions_cam.device
    scene = data.scene
    pixels = torch.randint(0, data.images.shape[1] * data.camera.pixels, (rays,), generator=generator, device=device)
    origins, directions, rgba = data.rays(instance, pixels.cpu(), directions_cam.cpu())
    batch = RayBatch(origins.to(device), directions.to(device), rgba.to(device))
    mse, out = photometric_loss(
        params, field_cfg, batch, cfg.render, scene=scene, grid=grid_of(occupied, scene, device), random_background=True, generator=generator
    )
    loss = mse
    free = free_space_points(free_grid, scene, cfg.free_space_points, generator)
    if cfg.free_space_weight > 0 and free.shape[0]:
        sigma = field_cfg.density(params, scene.to_unit(free)[None])[0][0]
        step_length = 1.0 / cfg.render.samples_per_ray  # a render step across the unit cube
        loss = loss + cfg.free_space_weight * torch.mean(-torch.expm1(-sigma * step_length))
    return loss, {"mse": mse.detach(), "samples": out["samples"]}


# ---------------------------------------------------------------------------------------------
# Validation


@torch.no_grad()
def validate(net: HyperNetwork, data: CategoryData, views: dict[int, tuple], device) -> dict[str, float]:
    """Mean full-image and foreground PSNR of one held-out view per validation instance, each
    NeRF rendered with its generated grid, beside the blank-image floor of the same views."""
    net.eval()
    rows = []
    for instance, (c2w, target_rgba, camera) in views.items():
        params = net(torch.tensor([instance], device=device))
        grid = generated_grid(params, net.cfg.field, data.scene)
        out = render_image(params, net.cfg.field, c2w.to(device), camera, RenderConfig(), scene=data.scene, grid=grid)
        rows.append(image_quality(out["rgb"].cpu()[None], target_rgba[None], out["opacity"].cpu()[None]))
    net.train()
    return {key: sum(r[key] for r in rows) / len(rows) for key in ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg")}


def validation_views(data: CategoryData, count: int) -> dict[int, tuple]:
    """First held-out view of ``count`` instances spread over the codebook."""
    picks = sorted({round(i * (len(data.instances) - 1) / max(count - 1, 1)) for i in range(count)})
    out = {}
    for n in picks:
        test = load_views(data.root / data.instances[n].id, split="test")
        out[n] = (test.c2w[0], test.images[0], test.cameras[0])
    return out


# ---------------------------------------------------------------------------------------------
# Checkpoints and the exported prior


def save_checkpoint(run: Path, state: dict) -> None:
    tmp = run / (CHECKPOINT + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, run / CHECKPOINT)


# ---------------------------------------------------------------------------------------------
# The loop


def train(
    data_root: Path,
    run: Path,
    hcfg: HyperNetConfig,
    tcfg: TrainConfig,
    *,
    resume: bool = False,
    until: int | None = None,
    limit: int | None = None,
    progress: bool = True,
) -> dict:
    """Train (or resume) a prior on the train split of ``data_root``; returns the final summary.

    ``until`` stops after that many steps with a checkpoint (continue with ``resume``), so long
    runs can be done in time-boxed parts; the prior is exported when the last step is done.
    """
    workers = start_workers()
    device = workers.device
    run = Path(run)
    if workers.main:
        run.mkdir(parents=True, exist_ok=True)
    checkpoint = None
    if resume:
        if not (run / CHECKPOINT).is_file():
            raise FileNotFoundError(f"--resume: {run / CHECKPOINT} does not exist; start the run without --resume")
        checkpoint = torch.load(run / CHECKPOINT, map_location="cpu", weights_only=False)
        hcfg = config.from_dict(HyperNetConfig, checkpoint["hypernet"])
        tcfg = config.from_dict(TrainConfig, checkpoint["train"])
        log.info("resuming %s at step %d", run, checkpoint["step"])

    torch.manual_seed(tcfg.seed)
    data = load_category(data_root, "train", limit, progress=progress and workers.main)
    if tcfg.objects_per_step < 1 or tcfg.rays_per_step < tcfg.objects_per_step:
        raise ValueError("objects_per_step must be >= 1 and rays_per_step at least one ray per object")
    grids = shape_grids(data, tcfg.grid_resolution, progress=progress and workers.main, source=tcfg.occupancy)
    free_grids = free_space_grids(grids)
    log.info("training grids keep %.1f%% of the scene box on average", 100 * grids.float().mean().item())
    net = HyperNetwork(hcfg, len(data.instances), data.shape_index, seed=tcfg.seed).to(device)
    if workers.main:
        counts = net.head_parameter_counts()
        log.info("hypernetwork parameters: %s (total %d)", ", ".join(f"{k} {v:,}" for k, v in counts.items()), sum(counts.values()))
    # fused: one pass over each tensor per step instead of a dozen (the table head alone is 8M values)
    optimizer, scheduler = adam_with_decay(
        net.parameters(), lr=tcfg.lr, steps=tcfg.steps, final_lr_factor=tcfg.final_lr_factor, betas=tcfg.betas, fused=True
    )
    history: list[dict] = []
    start_step = 0
    elapsed_before = 0.0
    if checkpoint is not None:
        net.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        scheduler.load_state_dict(checkpoint["scheduler"])
        history = checkpoint["history"]
        start_step = checkpoint["step"]
        elapsed_before = checkpoint.get("elapsed_s", 0.0)
    model = torch.nn.parallel.DistributedDataParallel(net) if workers.world > 1 else net
    val_views = validation_views(data, tcfg.validation_instances) if workers.main and tcfg.validate_every > 0 else {}
    directions_cam = data.camera_directions()
    per_worker = max(1, tcfg.objects_per_step // workers.world)
    rays_per_object = tcfg.rays_per_step // (per_worker * workers.world)

    def state(step: int, elapsed: float) -> dict:
        return {
            "model": net.state_dict(), "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
            "step": step, "history": history, "elapsed_s": elapsed, "hypernet": config.to_dict(hcfg), "train": config.to_dict(tcfg),
        }

    started = time.perf_counter()
    window = {"time": started, "rays": 0, "samples": 0}
    stop = min(tcfg.steps, until) if until else tcfg.steps
    bar = tqdm(range(start_step, stop), desc="train", unit="step", initial=start_step, total=tcfg.steps, disable=not (progress and workers.main))
    for step in bar:
        generator = _step_generator(tcfg.seed, step, workers.rank, device)
        chosen = step_instances(len(data.instances), per_worker, tcfg.seed, step, workers)
        index = torch.tensor(chosen, device=device)
        params = model(index, tcfg.code_noise, generator) if tcfg.code_noise > 0 else model(index)
        loss = torch.zeros((), device=device)
        mse = torch.zeros((), device=device)
        samples = 0
        for b, n in enumerate(chosen):
            part, info = instance_loss(
                select(params, b), data, n, grids[data.instances[n].shape_index], free_grids[data.instances[n].shape_index], rays_per_object,
                directions_cam.to(device), tcfg, hcfg.field, generator,
            )
            loss = loss + part / len(chosen)
            mse = mse + info["mse"] / len(chosen)
            samples += int(info["samples"])
        if tcfg.code_penalty > 0:
            loss = loss + tcfg.code_penalty * code_penalty(*net.codes(index))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(net.parameters(), tcfg.grad_clip)
        optimizer.step()
        scheduler.step()
        window["rays"] += rays_per_object * len(chosen) * workers.world
        window["samples"] += samples * workers.world

        last = step == tcfg.steps - 1
        validating = bool(val_views) and (step % tcfg.validate_every == 0 or last)
        if workers.main and (step % tcfg.log_every == 0 or last or validating):
            now = time.perf_counter()
            seconds = max(now - window["time"], 1e-9)
            record = {
                "step": step,
                "loss": float(loss.detach()),
                "train_psnr": mse_to_psnr(float(mse)),
                "grad_norm": float(grad_norm),
                "lr": scheduler.get_last_lr()[0],
                "rays_per_s": window["rays"] / seconds,
                "samples_per_s": window["samples"] / seconds,
                "samples_per_ray": window["samples"] / max(window["rays"], 1),
                "elapsed_s": elapsed_before + now - started,
            }
            if validating:
                scores = validate(net, data, val_views, device)
                record.update({f"val_{key}": value for key, value in scores.items()})
            history.append(record)
            window = {"time": time.perf_counter(), "rays": 0, "samples": 0}
            bar.set_postfix(psnr=f"{record['train_psnr']:.2f}", **({"val": f"{record['val_psnr']:.2f}"} if "val_psnr" in record else {}))
        if workers.main and ((step + 1) % tcfg.checkpoint_every == 0 or step + 1 == stop):
            save_checkpoint(run, state(step + 1, elapsed_before + time.perf_counter() - started))

    summary = {}
    if workers.main and stop < tcfg.steps:
        log.info("stopped at step %d of %d; continue with --resume", stop, tcfg.steps)
    elif workers.main:
        wall = elapsed_before + time.perf_counter() - started
        summary = {
            "steps": tcfg.steps,
            "instances": len(data.instances),
            "shapes": data.shapes,
            "workers": workers.world,
            "threads_per_worker": torch.get_num_threads(),
            "wall_s": wall,
            "parameters": net.head_parameter_counts(),
            "final": history[-1] if history else {},
        }
        export_prior(run, net, data, {"train": config.to_dict(tcfg), "summary": summary})
        (run / "history.json").write_text(json.dumps(history, indent=2))
        log.info("prior written to %s (%d instances, %.0f s)", run, len(data.instances), wall)
    if workers.world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return summary
