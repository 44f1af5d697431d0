"""Single-view generalisation (the paper's Table 1): NeRFs of objects the prior never saw, from one
input view, scored at the object's 91 evaluation views.

Each test object gives its input view from its held-out frames (not among the 91 evaluation
views) and is scored at the 91 standard views. Rows:

- ``tto``: test-time optimisation of the codes (``model.optimize.tto``);
- ``tto_denoise``: TTO, then denoise-and-finetune (``model.denoise``) when a denoiser is given;
- ``single_view_fit``: a per-object fit (``model.optimize.fit``) on the single view;
- ``nearest``: the training instance whose render at the input pose is closest (TTO's start);
- ``mean_code``: the NeRF of the codebook's mean codes.

Metrics per row: full-image and foreground PSNR with the blank-image floors, SSIM, and FID on
EfficientNet-Lite0 ImageNet features (``model.prior.embedders``: Inception and LPIPS weights are
not available offline, so this is *not* Inception-FID). FID needs many images: it is computed over
all objects' evaluation renders of a row against all their ground truths, with ``scipy.linalg.sqrtm``.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy import linalg
from tqdm import tqdm

from model.data.dataset import Views, load_index, load_views
from model.denoise.finetune import DenoiseConfig
from model.eval.field import render_views
from model.eval.metrics import image_quality, ssim
from model.eval.prior import save_grid
from model.nerf import config
from model.nerf.fields import FieldParams
from model.nerf.images import composite_over
from model.nerf.occupancy import OccupancyConfig, OccupancyGrid
from model.nerf.renderer import RenderConfig
from model.optimize.fit import FitConfig, fit_object
from model.optimize.tto import TTOConfig, codebook, invert
from model.prior.codes import generated_grid
from model.prior.embedders import ImageEmbedder
from model.prior.io import Prior, load_prior

log = logging.getLogger(__name__)

ROWS = ("tto", "tto_denoise", "single_view_fit", "nearest", "mean_code")


@dataclass
class GeneralizationConfig:
    objects: int = 11
    """Test objects (distinct shapes first: colour variant 0 of each test-split mesh)."""
    input_frame: int = 0
    """Which held-out frame is the input view."""
    input_views: int = 1
    tto: TTOConfig = dataclass_field(default_factory=TTOConfig)
    denoise: DenoiseConfig = dataclass_field(default_factory=DenoiseConfig)
    """Denoise-and-finetune settings of the ``tto_denoise`` row."""
    fit_steps: int = 500
    """Steps of the single-view fit baseline (4096 rays a step: over 100 passes over its one view)."""
    rows: tuple[str, ...] = ROWS
    """Which rows to compute (``tto_denoise`` also needs a denoiser)."""
    grid_rows: int = 4
    """Objects shown in the PNG of renders."""
    grid_poses: tuple[int, ...] = (10, 40, 70)
    render: RenderConfig = dataclass_field(default_factory=RenderConfig)


def test_objects(data: Path, count: int) -> list[str]:
    """Test-split ids, one colour variant per mesh first, then the other variants."""
    entries = [e for e in load_index(data) if e.split == "test"]
    by_variant = sorted(entries, key=lambda e: (e.extra.get("variant", 0), e.id))
    seen, first, rest = set(), [], []
    for e in by_variant:
        shape = e.extra.get("shape_id", e.id)
        (rest if shape in seen else first).append(e.id)
        seen.add(shape)
    return (first + rest)[:count]


def mean_code_params(prior: Prior) -> FieldParams:
    shapes, colors = codebook(prior.net)
    with torch.no_grad():
        return prior.net.params_from_codes(prior.net.shape_codes.weight.mean(0, keepdim=True), colors.mean(0, keepdim=True))


def instance_params(prior: Prior, index: int) -> FieldParams:
    shapes, colors = codebook(prior.net)
    with torch.no_grad():
        return prior.net.params_from_codes(shapes[index : index + 1], colors[index : index + 1])


def fid_features(embedder: ImageEmbedder, rgb: torch.Tensor) -> np.ndarray:
    """Pooled EfficientNet-Lite0 features ``[N, 1280]`` of whole images ``[N, H, W, 3]`` (no crop, not normalised)."""
    out = []
    with torch.no_grad():
        for start in range(0, len(rgb), 32):
            x = rgb[start : start + 32].permute(0, 3, 1, 2).float()
            x = F.interpolate(x, size=(embedder.input_size, embedder.input_size), mode="bilinear", antialias=True, align_corners=False)
            out.append(embedder.net.features(embedder.normalise(x).to(embedder.device)).cpu().numpy())
    return np.concatenate(out).astype(np.float64)


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted on feature rows ``a [N, D]`` and ``b [M, D]``."""
    mu_a, mu_b = a.mean(0), b.mean(0)
    cov_a, cov_b = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    root = np.real(linalg.sqrtm(cov_a @ cov_b))
    return float(((mu_a - mu_b) ** 2).sum() + np.trace(cov_a + cov_b - 2 * root))


def _score(prior: Prior, params: FieldParams, grid: OccupancyGrid, views: Views, cfg: RenderConfig) -> tuple[dict, torch.Tensor]:
    rgb, opacity, _, _ = render_views(params, prior.net.cfg.field, views, cfg, grid, prior.scene)
    quality = image_quality(rgb, views.images, opacity, cfg.background)
    quality["ssim"] = ssim(rgb, composite_over(views.images, cfg.background))
    return quality, rgb


def _grid_of(prior: Prior, params: FieldParams, seed: int = 0) -> OccupancyGrid:
    return generated_grid(params, prior.net.cfg.field, prior.scene, seed=seed)


def generalization(run: Path, data: Path, cfg: GeneralizationConfig, *, denoiser: Path | None = None,
                   out: Path | None = None) -> dict:
    """The table over ``cfg.objects`` test objects; writes renders' PNG grid beside ``out`` when given."""
    prior = load_prior(run)
    field_cfg = prior.net.cfg.field
    embedder = ImageEmbedder()
    ids = test_objects(data, cfg.objects)
    if not ids:
        raise ValueError(f"{data} has no test-split objects to evaluate on")
    denoise = _load_denoiser(denoiser, cfg.denoise) if denoiser is not None else None
    rows = [r for r in cfg.rows if r != "tto_denoise" or denoise is not None]
    per_object: list[dict] = []
    features: dict[str, list[np.ndarray]] = {r: [] for r in (*rows, "ground_truth")}
    picture: list[list[torch.Tensor]] = []
    mean_params = mean_code_params(prior)
    mean_grid = _grid_of(prior, mean_params)
    for number, object_id in enumerate(tqdm(ids, desc="generalisation", unit="object")):
        held = load_views(data / object_id, "test")
        evaluation = load_views(data / object_id, "train")
        picks = [(cfg.input_frame + k) % len(held.files) for k in range(cfg.input_views)]
        inputs = held.subset(picks)
        record = {"id": object_id, "rows": {}}
        renders: dict[str, torch.Tensor] = {}

        start = time.perf_counter()
        result = invert(prior.net, prior.scene, inputs.images, inputs.c2w, inputs.cameras, cfg.tto)
        record["tto_s"] = time.perf_counter() - start
        record["tto_init"] = result.init
        record["tto_history"] = result.history
        made = {"tto": (result.params, result.grid)}
        if result.init.startswith("nearest:"):
            nearest = int(result.init.split(":")[1])
            made["nearest"] = (instance_params(prior, nearest), None)
            record["nearest_instance"] = prior.instances[nearest]["id"]
        made["mean_code"] = (mean_params, mean_grid)
        if denoise is not None and "tto_denoise" in rows:
            start = time.perf_counter()
            made["tto_denoise"] = denoise(prior, result.params, (inputs.images, result.c2w, inputs.cameras))
            record["tto_denoise_s"] = time.perf_counter() - start
        if "single_view_fit" in rows:
            start = time.perf_counter()
            fit = fit_object(inputs, FitConfig(field=field_cfg, steps=cfg.fit_steps, occupancy=OccupancyConfig(seed=cfg.tto.seed), seed=cfg.tto.seed),
                             progress=False)
            record["fit_s"] = time.perf_counter() - start
            made["single_view_fit"] = (fit.params, fit.grid)

        for row in rows:
            if row not in made:
                continue
            params, grid = made[row]
            grid = grid if grid is not None else _grid_of(prior, params)
            quality, rgb = _score(prior, params, grid, evaluation, cfg.render)
            record["rows"][row] = quality
            renders[row] = rgb
            features[row].append(fid_features(embedder, rgb))
        truth = composite_over(evaluation.images, cfg.render.background)
        features["ground_truth"].append(fid_features(embedder, truth))
        per_object.append(record)
        log.info("%s: %s", object_id, {r: round(q["psnr_fg"], 2) for r, q in record["rows"].items()})
        if number < cfg.grid_rows:
            shown = [p % len(evaluation.files) for p in cfg.grid_poses]
            picture.append([composite_over(inputs.images[0], cfg.render.background)] + [truth[p] for p in shown])
            for row in rows:
                if row in renders:
                    picture.append([torch.ones_like(truth[0])] + [renders[row][p] for p in shown])

    truth_features = np.concatenate(features["ground_truth"])
    table = {}
    for row in rows:
        scored = [r["rows"][row] for r in per_object if row in r["rows"]]
        if not scored:
            continue
        table[row] = {key: float(np.mean([s[key] for s in scored])) for key in ("psnr", "psnr_fg", "ssim")}
        table[row]["fid"] = frechet_distance(np.concatenate(features[row]), truth_features)
        table[row]["objects"] = len(scored)
    report = {
        "rows": table,
        "objects": len(per_object),
        "resolution": int(prior.meta["camera"]["width"]),
        "input_views": cfg.input_views,
        "evaluation_views": len(load_views(data / ids[0], "train").files),
        "floor_psnr": float(np.mean([next(iter(r["rows"].values()))["floor_psnr"] for r in per_object])),
        "floor_psnr_fg": float(np.mean([next(iter(r["rows"].values()))["floor_psnr_fg"] for r in per_object])),
        "fid_features": "EfficientNet-Lite0 ImageNet pooled features (1280-d), not Inception",
        "tto_s": float(np.mean([r["tto_s"] for r in per_object])),
        "fit_s": float(np.mean([r["fit_s"] for r in per_object])) if "single_view_fit" in rows else None,
        "tto_denoise_s": float(np.mean([r["tto_denoise_s"] for r in per_object])) if "tto_denoise" in rows else None,
        "config": config.to_dict(cfg),
        "denoise": config.to_dict(cfg.denoise) if "tto_denoise" in rows else None,
        "per_object": per_object,
    }
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=2))
        if picture:
            save_grid(out.with_suffix(".png"), picture)
    return report


def _load_denoiser(path: Path, settings: DenoiseConfig):
    """``(prior, params, inputs) -> (params, grid)``: denoise-and-finetune with ``settings``
    (recorded in the report) and the denoiser at ``path``."""
    from model.denoise import denoise_and_finetune_prior

    return denoise_and_finetune_prior(path, settings)
