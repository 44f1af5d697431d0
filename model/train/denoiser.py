"""Training the image-to-image denoiser (paper section 3.1, step 2) on renders of the prior.

Pairs are (render of the prior's NeRF of a training instance at one of its training poses, that
view's ground truth), scored by L2 on colour over white and alpha, as the paper trains VQ-VAE-2.
Besides the instances' own codes, some pairs render NeRFs of *perturbed* codes (Gaussian noise at
a fraction of the codebook's per-dimension spread) against the same ground truth: a code near,
but not at, the instance's gives the floaters, holes and haze a test-time optimisation leaves,
which the instances' own NeRFs (fitted to these very views) rarely show. Optionally
(``tto_objects``), objects the prior never saw (the dataset's validation split, or a dataset of
deformed copies of the training meshes, ``tto_data``; never a test split) are inverted by
single-view TTO and their training views rendered from the result: the haze TTO leaves on an
unseen shape itself, paired with that shape's ground truth; ``tto_inputs`` inverts each object
from that many of its test views, one TTO each, for as many kinds of haze per shape.

Renders are computed once and cached on disk (``OUT/pairs/``: one safetensors file of uint8
images per instance, keyed by the prior's sha256 and the pair settings), so a rerun or a resumed
run renders nothing, and a run on more instances renders only the new ones. Validation pairs are
held-out views (the test frames) of a few training instances. Training draws random crops with horizontal flips, uses Adam with an exponential
decay, writes resumable checkpoints (safetensors + JSON, ``OUT/checkpoint/``) and is seedable:
the randomness of a step depends only on (seed, step), so a resumed run continues exactly as an
uninterrupted one. The trained denoiser is written with ``model.denoise.io.save_denoiser``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from model.data.dataset import load_index, load_views
from model.denoise.io import save_denoiser
from model.denoise.vqvae import (
    DenoiserConfig,
    VQVAE2Denoiser,
    rgba_channels,
    straight_rgba,
    to_channels,
)
from model.eval.metrics import image_quality
from model.nerf import config
from model.nerf.images import to_uint8
from model.nerf.renderer import RenderConfig, render_image
from model.optimize.step import adam_with_decay, mse_to_psnr
from model.optimize.tto import TTOConfig, invert
from model.prior.codes import generated_grid
from model.prior.io import PRIOR_WEIGHTS, Prior, load_prior

log = logging.getLogger(__name__)

PAIRS_DIR = "pairs"
PAIRS_KEY = "pairs.json"
CHECKPOINT_DIR = "checkpoint"


@dataclass
class PairsConfig:
    """Which renders pair with which ground truth."""

    instances: int = 0  # training instances rendered (spread over the codebook); 0: all
    clean_views: int = 4  # training views rendered from each instance's own codes
    perturbed_nerfs: int = 1  # NeRFs of perturbed codes per instance
    perturbed_views: int = 2  # training views rendered from each of them
    code_noise: tuple[float, float] = (0.25, 0.75)  # noise range, in units of the codebook's per-dimension std
    tto_objects: int = 0  # objects the prior never saw inverted by TTO from their first test view (0: none)
    tto_views: int = 24  # training views of each rendered from its TTO NeRF
    tto_inputs: int = 1  # single-view TTOs per object, each from another test view (spread over them)
    tto_data: str = ""  # the dataset they come from (default: the prior's); never its test split
    validation_instances: int = 8
    validation_views: int = 2  # held-out (test-frame) views per validation instance
    render: RenderConfig = field(default_factory=RenderConfig)
    seed: int = 0


@dataclass
class DenoiserTrainConfig:
    denoiser: DenoiserConfig = field(default_factory=DenoiserConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    steps: int = 1200
    batch: int = 8
    crop: int = 64  # side of the random training crops (0: whole images)
    lr: float = 1e-3
    final_lr_factor: float = 0.1
    latent_weight: float = 1.0
    tto_share: float = 0.0
    """Chance that a batch element is a TTO pair (0: every pair equally likely). The prior's own
    renders are near their ground truth and outnumber the TTO pairs, teaching a near identity."""
    validate_every: int = 250
    checkpoint_every: int = 250
    log_every: int = 25
    seed: int = 0


# ---------------------------------------------------------------------------------------------
# Pairs


def prior_digest(run: Path) -> str:
    """sha256 of the prior's weights: the cache key of renders made from it."""
    digest = hashlib.sha256()
    with open(Path(run) / PRIOR_WEIGHTS, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _render_pairs(prior: Prior, params, views, render_cfg: RenderConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 denoiser inputs and targets ``[V, H, W, 4]`` (colour over white and alpha) of ``views``."""
    grid = generated_grid(params, prior.net.cfg.field, prior.scene)
    outs = [render_image(params, prior.net.cfg.field, c2w, camera, render_cfg, scene=prior.scene, grid=grid) for c2w, camera in zip(views.c2w, views.cameras)]
    inputs = to_channels(torch.stack([o["rgb"] for o in outs]), torch.stack([o["opacity"] for o in outs]))
    targets = rgba_channels(views.images)
    return (torch.from_numpy(to_uint8(inputs.permute(0, 2, 3, 1))), torch.from_numpy(to_uint8(targets.permute(0, 2, 3, 1))))


@torch.no_grad()
def instance_pairs(prior: Prior, data: Path, instance: int, cfg: PairsConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The training pairs of one instance: renders of its own NeRF and of perturbed-code NeRFs."""
    net = prior.net
    generator = torch.Generator().manual_seed(cfg.seed * 1_000_003 + instance)
    views = load_views(data / prior.instances[instance]["id"], split="train")
    shape, color = net.codes(torch.tensor([instance], device=prior.device))
    shape_std, color_std = net.shape_codes.weight.std(0), net.color_codes.weight.std(0)
    picks = torch.randperm(len(views.files), generator=generator)
    parts = [_render_pairs(prior, net.params_from_codes(shape, color), views.subset(picks[: cfg.clean_views].tolist()), cfg.render)]
    used = cfg.clean_views
    low, high = cfg.code_noise
    for _ in range(cfg.perturbed_nerfs):
        level = low + (high - low) * torch.rand((), generator=generator).item()
        noisy_shape = shape + level * shape_std * torch.randn(shape.shape, generator=generator).to(shape.device)
        noisy_color = color + level * color_std * torch.randn(color.shape, generator=generator).to(color.device)
        chosen = picks[used : used + cfg.perturbed_views].tolist() or picks[: cfg.perturbed_views].tolist()
        used += cfg.perturbed_views
        parts.append(_render_pairs(prior, net.params_from_codes(noisy_shape, noisy_color), views.subset(chosen), cfg.render))
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


TTO_FIELDS = ("tto_objects", "tto_views", "tto_data", "tto_inputs")


def tto_objects(data: Path, prior: Prior, count: int) -> list[str]:
    """``count`` objects of ``data`` outside its test split that are not prior instances (its
    validation objects, or shapes the prior never saw such as deformed copies of its meshes),
    spread evenly over them in id order."""
    seen = {inst["id"] for inst in prior.instances}
    found = sorted(e.id for e in load_index(data) if e.split != "test" and e.id not in seen)
    if len(found) < count:
        raise ValueError(f"{data} has {len(found)} objects outside its test split that the prior did not train on; ask for at most that many TTO objects")
    return [found[n] for n in spread(count, len(found))]


def tto_input_views(data: Path, object_id: str, count: int) -> list[int]:
    """The test views of an unseen object that its ``count`` TTOs start from, spread over them (the first is view 0)."""
    return spread(count, len(load_views(data / object_id, split="test").files))


def tto_pairs_file(object_id: str, view: int) -> str:
    """Cache file of the pairs of ``object_id`` inverted from its test view ``view``."""
    return f"tto-{object_id}.safetensors" if view == 0 else f"tto-{object_id}-view{view}.safetensors"


def tto_object_pairs(prior: Prior, data: Path, object_id: str, cfg: PairsConfig, view: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs of an unseen object: its NeRF from single-view TTO (of its test view ``view``) rendered
    at ``cfg.tto_views`` of its training views, against their ground truth."""
    held = load_views(data / object_id, split="test").subset([view])
    result = invert(prior.net, prior.scene, held.images, held.c2w, held.cameras, TTOConfig(seed=cfg.seed))
    views = load_views(data / object_id, split="train")
    picks = spread(cfg.tto_views, len(views.files))
    params = {k: v.to(prior.device) for k, v in result.params.items()}
    return _render_pairs(prior, params, views.subset(picks), cfg.render)


def spread(count: int, instances: int) -> list[int]:
    """``count`` instance numbers spread evenly over ``instances``."""
    return sorted({round(i * (instances - 1) / max(count - 1, 1)) for i in range(min(count, instances))})


@torch.no_grad()
def validation_pairs(prior: Prior, data: Path, cfg: PairsConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Held-out pairs: the first test frames of a few instances, rendered from their own codes."""
    parts = []
    for n in spread(cfg.validation_instances, len(prior.instances)):
        views = load_views(data / prior.instances[n]["id"], split="test")
        parts.append(_render_pairs(prior, prior.net(torch.tensor([n], device=prior.device)), views.subset(slice(0, cfg.validation_views)), cfg.render))
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


def _atomic_save(tensors: dict[str, torch.Tensor], path: Path) -> None:
    tmp = path.with_suffix(".tmp")
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp))
    os.replace(tmp, path)


def cached_pairs(run: Path, data: Path, out: Path, cfg: PairsConfig, *, progress: bool = True) -> dict[str, torch.Tensor]:
    """Training and validation pairs (uint8 ``[N, H, W, 4]`` each: ``inputs``, ``targets``,
    ``val_inputs``, ``val_targets``), rendered once into ``out/pairs`` and read back afterwards."""
    if cfg.tto_objects and cfg.tto_inputs < 1:
        raise ValueError(f"tto_inputs is the number of TTOs per TTO object, at least 1; got {cfg.tto_inputs}")
    folder = Path(out) / PAIRS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    # an instance's renders do not depend on how many instances are used, so that is not in the
    # key; the TTO pairs have their own files and key
    digest = prior_digest(run)
    settings = config.to_dict(cfg)
    key = {"prior": digest, "pairs": {k: v for k, v in settings.items() if k != "instances" and k not in TTO_FIELDS}}
    key_file = folder / PAIRS_KEY
    if key_file.is_file() and json.loads(key_file.read_text()) != key:
        raise ValueError(f"{folder} holds renders of another prior or other pair settings; delete it or choose another --out")
    key_file.write_text(json.dumps(key, indent=2))
    prior = load_prior(run)
    for n, inst in enumerate(prior.instances):
        if not (Path(data) / inst["id"]).is_dir():
            raise FileNotFoundError(f"instance {inst['id']!r} of the prior is not in {data}; pass the dataset the prior was trained on")
    inputs, targets = [], []
    chosen = spread(cfg.instances, len(prior.instances)) if cfg.instances > 0 else range(len(prior.instances))
    bar = tqdm(chosen, desc="render pairs", unit="instance", disable=not progress)
    for n in bar:
        path = folder / f"{n:05d}.safetensors"
        if not path.is_file():
            x, y = instance_pairs(prior, Path(data), n, cfg)
            _atomic_save({"inputs": x, "targets": y}, path)
        stored = load_file(str(path))
        inputs.append(stored["inputs"])
        targets.append(stored["targets"])
    if cfg.tto_objects:
        tto_data = Path(cfg.tto_data) if cfg.tto_data else Path(data)
        tto_key = {"prior": digest, "tto_views": cfg.tto_views, "tto_data": str(tto_data), "render": settings["render"], "seed": cfg.seed}
        tto_key_file = folder / "tto-pairs.json"
        if tto_key_file.is_file() and json.loads(tto_key_file.read_text()) != tto_key:
            raise ValueError(f"{folder} holds TTO renders of other settings; delete its tto-* files or choose another --out")
        tto_key_file.write_text(json.dumps(tto_key, indent=2))
        # each (object, input view) has its own file, so asking for more inputs renders only the new ones
        runs = [(object_id, view) for object_id in tto_objects(tto_data, prior, cfg.tto_objects)
                for view in tto_input_views(tto_data, object_id, cfg.tto_inputs)]
        for object_id, view in tqdm(runs, desc="TTO pairs", unit="TTO", disable=not progress):
            path = folder / tto_pairs_file(object_id, view)
            if not path.is_file():
                x, y = tto_object_pairs(prior, tto_data, object_id, cfg, view)
                _atomic_save({"inputs": x, "targets": y}, path)
            stored = load_file(str(path))
            inputs.append(stored["inputs"])
            targets.append(stored["targets"])
    val_path = folder / "validation.safetensors"
    if not val_path.is_file():
        x, y = validation_pairs(prior, Path(data), cfg)
        _atomic_save({"inputs": x, "targets": y}, val_path)
    val = load_file(str(val_path))
    tto_count = sum(len(x) for x in inputs[len(chosen):])
    return {"inputs": torch.cat(inputs), "targets": torch.cat(targets), "val_inputs": val["inputs"], "val_targets": val["targets"],
            "tto_pairs": torch.tensor(tto_count)}


# ---------------------------------------------------------------------------------------------
# Batches, validation


def as_channels(images: torch.Tensor) -> torch.Tensor:
    """uint8 ``[N, H, W, 4]`` -> float ``[N, 4, H, W]`` in [0, 1]."""
    return images.permute(0, 3, 1, 2).float() / 255.0


def training_batch(pairs: dict[str, torch.Tensor], cfg: DenoiserTrainConfig, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A random batch of crops ``[B, 4, c, c]`` (inputs, targets), half of them mirrored left-right;
    with ``cfg.tto_share`` each element is a TTO pair (the last ``pairs["tto_pairs"]``) with that chance."""
    count, height, width = pairs["inputs"].shape[:3]
    picks = torch.randint(0, count, (cfg.batch,), generator=generator)
    tto = int(pairs.get("tto_pairs", 0))
    if cfg.tto_share > 0 and 0 < tto < count:
        from_tto = torch.rand(cfg.batch, generator=generator) < cfg.tto_share
        picks = torch.where(from_tto, count - tto + torch.randint(0, tto, (cfg.batch,), generator=generator),
                            torch.randint(0, count - tto, (cfg.batch,), generator=generator))
    x, y = as_channels(pairs["inputs"][picks]), as_channels(pairs["targets"][picks])
    if 0 < cfg.crop < min(height, width):
        top = torch.randint(0, height - cfg.crop + 1, (cfg.batch,), generator=generator)
        left = torch.randint(0, width - cfg.crop + 1, (cfg.batch,), generator=generator)
        x = torch.stack([x[b, :, t : t + cfg.crop, l : l + cfg.crop] for b, (t, l) in enumerate(zip(top.tolist(), left.tolist()))])
        y = torch.stack([y[b, :, t : t + cfg.crop, l : l + cfg.crop] for b, (t, l) in enumerate(zip(top.tolist(), left.tolist()))])
    flip = torch.rand(cfg.batch, generator=generator) < 0.5
    x[flip], y[flip] = x[flip].flip(-1), y[flip].flip(-1)
    return x, y


def denoiser_loss(denoiser: VQVAE2Denoiser, x: torch.Tensor, y: torch.Tensor, latent_weight: float) -> tuple[torch.Tensor, dict]:
    """L2 on colour over white and alpha plus the quantisers' latent loss."""
    out = denoiser(x)
    mse = F.mse_loss(out.image, y)
    return mse + latent_weight * out.latent_loss, {"mse": mse.detach(), "latent": out.latent_loss.detach(), "perplexity": [float(p) for p in out.perplexity]}


def _quality(channels: torch.Tensor, targets: torch.Tensor) -> dict:
    """Full and foreground PSNR of denoiser-layout images ``[N, 4, H, W]`` against targets in that layout."""
    quality = image_quality(channels[:, :3].permute(0, 2, 3, 1), straight_rgba(targets), channels[:, 3])
    return {"psnr": quality["psnr"], "psnr_fg": quality["psnr_fg"]}


@torch.no_grad()
def validate(denoiser: VQVAE2Denoiser, pairs: dict[str, torch.Tensor], batch: int = 8) -> dict[str, float]:
    """PSNR of the raw renders and of their denoised versions on the validation pairs (full images)."""
    denoiser.eval()
    x, y = as_channels(pairs["val_inputs"]), as_channels(pairs["val_targets"])
    out = torch.cat([denoiser(x[i : i + batch]).image for i in range(0, x.shape[0], batch)])
    denoiser.train()
    raw, denoised = _quality(x, y), _quality(out, y)
    return {"raw_psnr": raw["psnr"], "raw_psnr_fg": raw["psnr_fg"], "psnr": denoised["psnr"], "psnr_fg": denoised["psnr_fg"]}


# ---------------------------------------------------------------------------------------------
# Checkpoints (safetensors + JSON: no pickle)


def save_checkpoint(out: Path, denoiser: VQVAE2Denoiser, optimizer, scheduler, state: dict) -> None:
    """Weights and Adam moments in ``checkpoint/state.safetensors``, the rest in ``state.json``;
    each written to a temporary file and renamed, the JSON last (it marks the checkpoint complete)."""
    folder = Path(out) / CHECKPOINT_DIR
    folder.mkdir(parents=True, exist_ok=True)
    tensors = {f"model.{k}": v.detach().clone() for k, v in denoiser.state_dict().items()}
    opt = optimizer.state_dict()
    for index, moments in opt["state"].items():
        tensors.update({f"optimizer.{index}.{name}": value.detach().clone() for name, value in moments.items()})
    _atomic_save(tensors, folder / "state.safetensors")
    meta = {**state, "param_groups": opt["param_groups"], "scheduler": scheduler.state_dict()}
    tmp = folder / "state.json.tmp"
    tmp.write_text(json.dumps(meta, indent=2))
    os.replace(tmp, folder / "state.json")


def load_checkpoint(out: Path) -> tuple[dict[str, torch.Tensor], dict[int, dict[str, torch.Tensor]], dict]:
    """(model state, Adam state per parameter index, metadata) of the checkpoint in ``out``."""
    folder = Path(out) / CHECKPOINT_DIR
    if not (folder / "state.json").is_file():
        raise FileNotFoundError(f"--resume: {folder / 'state.json'} does not exist; start the run without --resume")
    tensors = load_file(str(folder / "state.safetensors"))
    model = {k.removeprefix("model."): v for k, v in tensors.items() if k.startswith("model.")}
    moments: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        if key.startswith("optimizer."):
            _, index, name = key.split(".", 2)
            moments.setdefault(int(index), {})[name] = value
    return model, moments, json.loads((folder / "state.json").read_text())


# ---------------------------------------------------------------------------------------------
# The loop


def _step_generator(seed: int, step: int) -> torch.Generator:
    return torch.Generator().manual_seed((seed * 1_000_003 + step) % (2**63))


def train_denoiser(
    run: Path,
    data: Path,
    out: Path,
    cfg: DenoiserTrainConfig,
    *,
    resume: bool = False,
    until: int | None = None,
    progress: bool = True,
) -> dict:
    """Train (or resume) a denoiser on renders of the prior in ``run``; writes it into ``out``.

    ``until`` stops after that many steps with a checkpoint (continue with ``resume``); the
    denoiser is written when the last step is done. Returns the summary (empty when stopped early).
    """
    out = Path(out)
    checkpoint = load_checkpoint(out) if resume else None
    if checkpoint is not None:
        cfg = config.from_dict(DenoiserTrainConfig, checkpoint[2]["train"])
        log.info("resuming %s at step %d", out, checkpoint[2]["step"])
    if cfg.steps < 1 or cfg.batch < 1 or cfg.crop < 0 or not 0.0 <= cfg.tto_share <= 1.0:
        raise ValueError("denoiser training needs steps >= 1, batch >= 1, crop >= 0 and a TTO share in [0, 1]")
    torch.manual_seed(cfg.seed)
    pairs = cached_pairs(Path(run), Path(data), out, cfg.pairs, progress=progress)
    log.info("%d training pairs, %d validation pairs of %dx%d", len(pairs["inputs"]), len(pairs["val_inputs"]), pairs["inputs"].shape[2], pairs["inputs"].shape[1])
    denoiser = VQVAE2Denoiser(cfg.denoiser)
    optimizer, scheduler = adam_with_decay(denoiser.parameters(), lr=cfg.lr, steps=cfg.steps, final_lr_factor=cfg.final_lr_factor)
    history: list[dict] = []
    start_step, elapsed_before = 0, 0.0
    if checkpoint is not None:
        model_state, moments, meta = checkpoint
        denoiser.load_state_dict(model_state)
        optimizer.load_state_dict({"state": moments, "param_groups": meta["param_groups"]})
        scheduler.load_state_dict(meta["scheduler"])
        history, start_step, elapsed_before = meta["history"], meta["step"], meta["elapsed_s"]
    denoiser.train()
    began = time.perf_counter()
    stop = min(cfg.steps, until) if until else cfg.steps
    bar = tqdm(range(start_step, stop), desc="train denoiser", unit="step", initial=start_step, total=cfg.steps, disable=not progress)
    for step in bar:
        generator = _step_generator(cfg.seed, step)
        torch.manual_seed(int(torch.randint(0, 2**62, (), generator=generator)))  # codebook restarts draw from the global stream
        x, y = training_batch(pairs, cfg, generator)
        loss, info = denoiser_loss(denoiser, x, y, cfg.latent_weight)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        last = step == cfg.steps - 1
        validating = cfg.validate_every > 0 and (step % cfg.validate_every == 0 or last)
        if step % cfg.log_every == 0 or last or validating:
            record = {
                "step": step, "loss": float(loss.detach()), "mse": float(info["mse"]), "train_psnr": mse_to_psnr(float(info["mse"])),
                "latent_loss": float(info["latent"]), "perplexity_top": info["perplexity"][0], "perplexity_bottom": info["perplexity"][1],
                "lr": scheduler.get_last_lr()[0], "elapsed_s": elapsed_before + time.perf_counter() - began,
            }
            if validating:
                record.update({f"val_{k}": v for k, v in validate(denoiser, pairs).items()})
            history.append(record)
            bar.set_postfix(psnr=f"{record['train_psnr']:.2f}", **({"val": f"{record['val_psnr']:.2f}/{record['val_raw_psnr']:.2f}"} if validating else {}))
        if (step + 1) % cfg.checkpoint_every == 0 or step + 1 == stop:
            state = {"step": step + 1, "history": history, "elapsed_s": elapsed_before + time.perf_counter() - began, "train": config.to_dict(cfg)}
            save_checkpoint(out, denoiser, optimizer, scheduler, state)
    if stop < cfg.steps:
        log.info("stopped at step %d of %d; continue with --resume", stop, cfg.steps)
        return {}
    wall = elapsed_before + time.perf_counter() - began
    final = history[-1] if history else {}
    summary = {"steps": cfg.steps, "pairs": len(pairs["inputs"]), "validation_pairs": len(pairs["val_inputs"]), "wall_s": wall,
               "threads": torch.get_num_threads(), "parameters": sum(p.numel() for p in denoiser.parameters()), "final": final}
    extra = {"prior": {"run": str(run), "sha256": prior_digest(run)}, "data": str(data), "train": config.to_dict(cfg), "summary": summary}
    save_denoiser(out, denoiser.eval(), extra)
    (out / "history.json").write_text(json.dumps(history, indent=2))
    log.info("denoiser written to %s (%d steps, %.0f s)", out, cfg.steps, wall)
    return summary
