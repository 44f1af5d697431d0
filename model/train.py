"""Training the hypernetwork prior end to end through the renderer (paper section 3.1, step 1).

Each step draws several instances, runs the hypernetwork once for all of them, and renders a
share of the step's rays for each from its own training views, over a random background. Only
the learnable parts are the heads and the codebooks: the NeRFs are differentiable layers.

Modelling only what a scene needs: rays are marched only through each shape's visual hull
(carved from its masks, shared by its colour variants), so empty space costs no field evaluation.
Space outside the hull is never seen by a training ray, so a free-space loss pushes the density
of random points there to zero; the generated NeRFs then mark their own empty space and a grid
derived from their density (as the service builds one) matches the object.

Data parallel with ``torch.distributed``: ``torchrun --nproc_per_node=2 -m model.train ...`` runs
one process per core (gloo on CPU, NCCL on GPUs), each rendering different instances; gradients
are averaged by ``DistributedDataParallel``. Randomness of a step depends only on (seed, step,
rank), so a resumed run continues exactly as an uninterrupted one would.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
import torch.distributed as dist
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from model.category import OCCUPANCY_SOURCES, CategoryData, free_space_grids, free_space_points, grid_of, load_category, shape_grids
from model.data.dataset import load_views
from model.device import default_device
from model.evaluate import composite_over
from model.field import FieldParams, select
from model.fit import scene_box, unit_density_fn
from model.hypernet import HyperNetConfig, HyperNetwork, code_penalty, preset
from model.metrics import psnr
from model.occupancy import OccupancyGrid, grid_from_density
from model.renderer import RenderConfig, render_image, render_rays

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"
PRIOR_WEIGHTS = "hypernet.safetensors"
PRIOR_META = "prior.json"


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
    free_space_weight: float = 0.1
    free_space_points: int = 1024
    grid_resolution: int = 64
    occupancy: str = "hull"  # training occupancy: hull, mesh or box (model.category.shape_grids)
    render: RenderConfig = field(default_factory=lambda: RenderConfig(termination_threshold=0.0))
    validate_every: int = 500
    validation_instances: int = 4
    checkpoint_every: int = 500
    log_every: int = 50
    seed: int = 0

    def to_dict(self) -> dict:
        out = asdict(self)
        out["render"] = self.render.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        data = dict(data)
        data["render"] = RenderConfig.from_dict(data.get("render", {}))
        if "betas" in data:
            data["betas"] = tuple(data["betas"])
        return cls(**data)


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
    pixels = torch.randint(0, data.images.shape[1] * data.width * data.height, (rays,), generator=generator, device=device)
    origins, directions, rgba = data.rays(instance, pixels.cpu(), directions_cam.cpu())
    origins, directions, rgba = origins.to(device), directions.to(device), rgba.to(device)
    background = torch.rand(rays, 3, generator=generator, device=device)
    target = rgba[:, :3] * rgba[:, 3:] + background * (1 - rgba[:, 3:])
    grid = grid_of(occupied, device)
    out = render_rays(params, field_cfg, origins, directions, cfg.render, grid=grid, background=background, jitter=True, generator=generator)
    mse = torch.mean((out["rgb"] - target) ** 2)
    loss = mse
    free = free_space_points(free_grid, cfg.free_space_points, generator)
    if cfg.free_space_weight > 0 and free.shape[0]:
        lo, hi = scene_box(device)
        sigma = field_cfg.density(params, ((free - lo) / (hi - lo))[None])[0][0]
        step_length = float((hi - lo).max()) / cfg.render.samples_per_ray
        loss = loss + cfg.free_space_weight * torch.mean(-torch.expm1(-sigma * step_length))
    return loss, {"mse": mse.detach(), "samples": out["samples"]}


# ---------------------------------------------------------------------------------------------
# Validation


@torch.no_grad()
def generated_grid(params: FieldParams, field_cfg, device, resolution: int = 64, samples_per_cell: int = 2) -> OccupancyGrid:
    """The occupancy grid of a generated NeRF, from its own density (what the service caches)."""
    lo, hi = scene_box(device)
    return grid_from_density(unit_density_fn(params, field_cfg, device), lo, hi, resolution=resolution, samples_per_cell=samples_per_cell)


@torch.no_grad()
def validate(net: HyperNetwork, views: dict[int, tuple], device) -> float:
    """Mean PSNR of one held-out view per validation instance, each NeRF with its generated grid."""
    net.eval()
    scores = []
    for instance, (c2w, target, width, height, focal) in views.items():
        params = net(torch.tensor([instance], device=device))
        grid = generated_grid(params, net.cfg.field, device)
        out = render_image(params, net.cfg.field, c2w.to(device), width, height, focal, RenderConfig(), grid=grid)
        scores.append(psnr(out["rgb"].cpu(), target))
    net.train()
    return sum(scores) / len(scores)


def validation_views(data: CategoryData, count: int) -> dict[int, tuple]:
    """First held-out view of ``count`` instances spread over the codebook."""
    picks = sorted({round(i * (len(data.instances) - 1) / max(count - 1, 1)) for i in range(count)})
    out = {}
    for n in picks:
        test = load_views(data.root / data.instances[n].id, split="test")
        out[n] = (test.c2w[0], composite_over(test.images[0]), test.width, test.height, test.focal)
    return out


# ---------------------------------------------------------------------------------------------
# Checkpoints and the exported prior


def save_checkpoint(run: Path, state: dict) -> None:
    tmp = run / (CHECKPOINT + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, run / CHECKPOINT)


def export_prior(run: Path, net: HyperNetwork, data: CategoryData, tcfg: TrainConfig, extra: dict, dtype=torch.float16) -> Path:
    """The trained prior: weights (``dtype``, half by default to keep bundles small) and its metadata."""
    tensors = {k: v.detach().to(dtype if v.is_floating_point() else v.dtype).contiguous().cpu() for k, v in net.state_dict().items()}
    save_file(tensors, str(run / PRIOR_WEIGHTS))
    meta = {
        "hypernet": net.cfg.to_dict(),
        "train": tcfg.to_dict(),
        "data": str(data.root),
        "instances": [inst.to_json() for inst in data.instances],
        "camera": {"width": data.width, "height": data.height, "focal": data.focal},
        "weights_dtype": str(dtype).removeprefix("torch."),
        **extra,
    }
    (run / PRIOR_META).write_text(json.dumps(meta, indent=2))
    return run / PRIOR_WEIGHTS


def load_prior(run: Path, device=None) -> tuple[HyperNetwork, dict]:
    """The exported prior of a training run (weights promoted to float32) and its metadata."""
    run = Path(run)
    if not (run / PRIOR_WEIGHTS).is_file():
        raise FileNotFoundError(f"{run} holds no trained prior ({PRIOR_WEIGHTS}); run `hypnerf train` to the end first")
    meta = json.loads((run / PRIOR_META).read_text())
    cfg = HyperNetConfig.from_dict(meta["hypernet"])
    instances = meta["instances"]
    net = HyperNetwork(cfg, len(instances), [i["shape_index"] for i in instances])
    state = {k: (v.float() if v.is_floating_point() else v) for k, v in load_file(str(run / PRIOR_WEIGHTS)).items()}
    net.load_state_dict(state)
    return net.to(device or "cpu").eval(), meta


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
        hcfg = HyperNetConfig.from_dict(checkpoint["hypernet"])
        tcfg = TrainConfig.from_dict(checkpoint["train"])
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
    optimizer = torch.optim.Adam(net.parameters(), lr=tcfg.lr, betas=tcfg.betas, eps=1e-15, fused=True)
    decay = math.log(tcfg.final_lr_factor) / max(tcfg.steps, 1)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: math.exp(decay * step))
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
            "step": step, "history": history, "elapsed_s": elapsed, "hypernet": hcfg.to_dict(), "train": tcfg.to_dict(),
        }

    started = time.perf_counter()
    window = {"time": started, "rays": 0, "samples": 0}
    stop = min(tcfg.steps, until) if until else tcfg.steps
    bar = tqdm(range(start_step, stop), desc="train", unit="step", initial=start_step, total=tcfg.steps, disable=not (progress and workers.main))
    for step in bar:
        generator = _step_generator(tcfg.seed, step, workers.rank, device)
        chosen = step_instances(len(data.instances), per_worker, tcfg.seed, step, workers)
        index = torch.tensor(chosen, device=device)
        params = model(index)
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
                "train_psnr": -10 * math.log10(max(float(mse), 1e-10)),
                "grad_norm": float(grad_norm),
                "lr": scheduler.get_last_lr()[0],
                "rays_per_s": window["rays"] / seconds,
                "samples_per_s": window["samples"] / seconds,
                "samples_per_ray": window["samples"] / max(window["rays"], 1),
                "elapsed_s": elapsed_before + now - started,
            }
            if validating:
                record["val_psnr"] = validate(net, val_views, device)
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
        export_prior(run, net, data, tcfg, {"summary": summary})
        (run / "history.json").write_text(json.dumps(history, indent=2))
        log.info("prior written to %s (%d instances, %.0f s)", run / PRIOR_WEIGHTS, len(data.instances), wall)
    if workers.world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return summary


# ---------------------------------------------------------------------------------------------
# Command line (``hypnerf train`` and ``python -m model.train`` for torchrun)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = TrainConfig()
    parser.add_argument("--data", required=True, type=Path, help="dataset folder (its train split is used)")
    parser.add_argument("--out", required=True, type=Path, help="run folder: checkpoint, history, exported prior")
    parser.add_argument("--preset", default="cpu", help="hypernetwork size: paper, cpu, cpu-no-mrhe or tiny (default cpu)")
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--objects-per-step", type=int, default=defaults.objects_per_step)
    parser.add_argument("--rays", type=int, default=defaults.rays_per_step, help="rays per step over all objects")
    parser.add_argument("--lr", type=float, default=defaults.lr)
    parser.add_argument("--validate-every", type=int, default=defaults.validate_every, help="steps between validation renders (0: never)")
    parser.add_argument("--checkpoint-every", type=int, default=defaults.checkpoint_every)
    parser.add_argument("--limit", type=int, help="train on the first N instances only")
    parser.add_argument("--occupancy", choices=OCCUPANCY_SOURCES, default=defaults.occupancy,
                        help="where training rays take samples: the visual hull (default), cells at the ground-truth mesh surface, or the whole box")
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint (its settings win)")
    parser.add_argument("--until", type=int, help="stop after this step with a checkpoint (continue later with --resume)")


def run_from_args(args) -> int:
    if args.steps < 1:
        raise ValueError("--steps must be at least 1")
    tcfg = TrainConfig(
        steps=args.steps,
        objects_per_step=args.objects_per_step,
        rays_per_step=args.rays,
        lr=args.lr,
        validate_every=args.validate_every,
        checkpoint_every=args.checkpoint_every,
        occupancy=args.occupancy,
        seed=args.seed,
    )
    summary = train(args.data, args.out, preset(args.preset), tcfg, resume=args.resume, until=args.until, limit=args.limit)
    if summary:
        final = summary.get("final", {})
        print(f"trained {summary['instances']} instances in {summary['wall_s']:.0f} s; final train PSNR {final.get('train_psnr', float('nan')):.2f} dB -> {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    parser = argparse.ArgumentParser(prog="python -m model.train", description="Train the hypernetwork prior (torchrun-ready).")
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_from_args(args)
    except (ValueError, FileNotFoundError) as error:
        print(f"train: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
