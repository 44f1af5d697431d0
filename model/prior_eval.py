"""What a trained prior is worth: compression against per-object fits (paper Table 2 and the
ablation of Table 4) and shape/colour disentanglement (paper section 4.5).

Every generated NeRF is judged as the service would use it: the hypernetwork runs once on the
instance's codes, the occupancy grid comes from the NeRF's own density, and the renderer's fast
settings draw the fixed held-out views. Per-object fits of the same field architecture are the
reference (``hypnerf fit``; cached in a folder and reused when their settings match).

Colour distance is the CIE76 distance (Delta E) between the mean CIELAB colour of two images'
foreground pixels, converted with **scikit-image** (perceptually uniform, unlike RGB).
"""

from __future__ import annotations

import json
import logging
import math
import random
import statistics
from pathlib import Path

import numpy as np
import torch
import trimesh
from skimage.color import rgb2lab
from tqdm import tqdm

from model.data.dataset import load_views
from model.evaluate import evaluate_field, field_mesh, fit_and_evaluate
from model.field import FieldParams
from model.fit import FitConfig
from model.hypernet import HyperNetwork
from model.images import save_png
from model.mesh import export_mesh
from model.metrics import mesh_chamfer
from model.renderer import RenderConfig
from model.train import PRIOR_WEIGHTS, generated_grid, load_prior

log = logging.getLogger(__name__)


def instance_number(meta: dict, instance_id: str) -> int:
    ids = [inst["id"] for inst in meta["instances"]]
    if instance_id not in ids:
        raise ValueError(f"{instance_id!r} is not an instance of this prior; `hypnerf eval` lists them in prior.json")
    return ids.index(instance_id)


@torch.no_grad()
def generate(net: HyperNetwork, instance: int) -> FieldParams:
    device = next(net.parameters()).device
    return net(torch.tensor([instance], device=device))


@torch.no_grad()
def swap_codes(net: HyperNetwork, shape_instance: int, color_instance: int) -> FieldParams:
    """The NeRF of one instance's shape code with another instance's colour code."""
    device = next(net.parameters()).device
    shape_code, _ = net.codes(torch.tensor([shape_instance], device=device))
    _, color_code = net.codes(torch.tensor([color_instance], device=device))
    return net.params_from_codes(shape_code, color_code)


def spread_instances(meta: dict, count: int) -> list[int]:
    """``count`` instances spread over the codebook, one per shape while shapes last."""
    instances = meta["instances"]
    by_shape: dict[int, list[int]] = {}
    for n, inst in enumerate(instances):
        by_shape.setdefault(inst["shape_index"], []).append(n)
    rounds = max(len(v) for v in by_shape.values())
    ordered = [members[r] for r in range(rounds) for members in by_shape.values() if r < len(members)]
    if count >= len(ordered):
        return ordered
    shapes = len(by_shape)
    first = ordered[:shapes]
    if count <= shapes:
        step = shapes / count
        return [first[int(i * step)] for i in range(count)]
    return ordered[:count]


def _mean(rows: list[dict], key: str) -> float | None:
    values = [r[key] for r in rows if r.get(key) is not None]
    return statistics.fmean(values) if values else None


def _summary(rows: list[dict]) -> dict:
    return {key: _mean(rows, key) for key in ("psnr", "ssim", "chamfer", "render_ms")}


def evaluate_generated(net: HyperNetwork, params: FieldParams, test_views, mesh_resolution: int) -> tuple[dict, torch.Tensor, trimesh.Trimesh]:
    device = next(iter(params.values())).device
    grid = generated_grid(params, net.cfg.field, device)
    metrics, renders, mesh = evaluate_field(params, net.cfg.field, grid, test_views, RenderConfig(), mesh_resolution=mesh_resolution)
    metrics["occupied_fraction"] = grid.fraction
    return metrics, renders, mesh


def per_object_fit(root: Path, object_id: str, fits: Path, cfg: FitConfig, device, mesh_resolution: int) -> tuple[dict, int]:
    """Metrics and checkpoint bytes of a per-object fit, reusing one already in ``fits`` with the same settings."""
    out = fits / object_id
    metrics_file, config_file = out / "metrics.json", out / "config.json"
    if metrics_file.is_file() and config_file.is_file():
        saved = json.loads(config_file.read_text())
        if FitConfig.from_dict(saved["fit"]) == cfg and Path(saved.get("data", "")) == root.resolve():
            log.info("reusing the per-object fit of %s in %s", object_id, out)
            return json.loads(metrics_file.read_text()), (out / "field.safetensors").stat().st_size
    metrics = fit_and_evaluate(root, object_id, out, cfg, device, mesh_resolution)
    return metrics, (out / "field.safetensors").stat().st_size


def compression(
    run: Path,
    data_root: Path,
    *,
    objects: int = 10,
    fits: Path | None = None,
    fit_steps: int | None = None,
    mesh_resolution: int = 128,
    ablation: str | None = None,
    device=None,
) -> dict:
    """Generated NeRFs of ``objects`` training instances vs per-object fits of the same instances.

    The per-object fits use the hash-grid field of the fit defaults unless the prior emits a
    hash-grid field, in which case they use exactly the prior's field (the paper's "same
    architecture"). For the ablation without MRHE the reference stays the hash-grid fit, as in
    the paper where InstantNGP is the reference of both tables.
    """
    device = device or "cpu"
    net, meta = load_prior(run, device)
    field_kind = net.cfg.field.to_dict()["kind"]
    if ablation == "no-mrhe" and field_kind == "hashgrid":
        raise ValueError(f"{run} is a hash-grid prior; the no-mrhe ablation needs a run trained with --preset cpu-no-mrhe")
    if ablation is None and field_kind != "hashgrid":
        raise ValueError(f"{run} emits a {field_kind} field; evaluate it with --ablation no-mrhe")
    fit_cfg = FitConfig() if field_kind != "hashgrid" else FitConfig(field=net.cfg.field)
    if fit_steps:
        fit_cfg.steps = fit_steps
    fits = Path(fits) if fits else Path(run) / "per-object-fits"
    rows = []
    fit_bytes = []
    for n in tqdm(spread_instances(meta, objects), desc="compression", unit="object"):
        object_id = meta["instances"][n]["id"]
        test = load_views(Path(data_root) / object_id, split="test")
        generated, _, _ = evaluate_generated(net, generate(net, n), test, mesh_resolution)
        reference, size = per_object_fit(Path(data_root), object_id, fits, fit_cfg, device, mesh_resolution)
        fit_bytes.append(size)
        rows.append({"object": object_id, "hypernet": _pick(generated), "per_object": _pick(reference)})
        log.info("%s: hypernet %.2f dB, per-object %.2f dB", object_id, generated["psnr"], reference["psnr"])
    hyper = _summary([r["hypernet"] for r in rows])
    single = _summary([r["per_object"] for r in rows])
    prior_bytes = (Path(run) / PRIOR_WEIGHTS).stat().st_size
    instances = len(meta["instances"])
    # storage is compared at the prior's own precision: a fit's file also holds float32 weights and
    # its occupancy grid, which a generated NeRF rebuilds from its density instead of storing
    fit_parameters = sum(math.prod(shape) for shape in fit_cfg.field.param_shapes().values())
    itemsize = torch.empty((), dtype=getattr(torch, meta.get("weights_dtype", "float32"))).element_size()
    per_object_bytes = fit_parameters * itemsize
    return {
        "hypernet": hyper,
        "per_object": single,
        "objects": len(rows),
        "psnr_gap_db": single["psnr"] - hyper["psnr"],
        "field": field_kind,
        "per_object_field": fit_cfg.field.to_dict()["kind"],
        "per_object_steps": fit_cfg.steps,
        "storage": {
            "prior_bytes": prior_bytes,
            "prior_instances": instances,
            "weights_dtype": meta.get("weights_dtype", "float32"),
            "per_object_parameters": fit_parameters,
            "per_object_bytes": per_object_bytes,
            "per_object_bytes_for_all_instances": per_object_bytes * instances,
            "compression_ratio": per_object_bytes * instances / prior_bytes,
            "per_object_file_bytes_mean": statistics.fmean(fit_bytes),
        },
        "rows": rows,
        "run": str(run),
        "data": str(data_root),
    }


def _pick(metrics: dict) -> dict:
    return {k: metrics.get(k) for k in ("psnr", "ssim", "chamfer", "render_ms", "samples_per_ray")}


# ---------------------------------------------------------------------------------------------
# Disentanglement


def foreground_lab(images: torch.Tensor, alpha: torch.Tensor) -> np.ndarray:
    """Mean CIELAB colour of pixels with ``alpha > 0.5``; ``images [V, H, W, 3]`` in [0, 1]."""
    mask = (alpha > 0.5).cpu().numpy()
    pixels = images.clamp(0, 1).cpu().numpy()[mask]
    if pixels.size == 0:
        return np.full(3, np.nan)
    return rgb2lab(pixels[None].astype(np.float64))[0].mean(axis=0)


def colour_distance(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b))


def render_swap(net: HyperNetwork, params: FieldParams, views, mesh_resolution: int) -> tuple[torch.Tensor, torch.Tensor, trimesh.Trimesh]:
    """Renders (with opacity) and mesh of a generated NeRF at the poses of ``views``."""
    from model.renderer import render_image

    device = next(net.parameters()).device
    grid = generated_grid(params, net.cfg.field, device)
    rgb, alpha = [], []
    for c2w in views.c2w:
        out = render_image(params, net.cfg.field, c2w.to(device), views.width, views.height, views.focal, RenderConfig(), grid=grid)
        rgb.append(out["rgb"].cpu())
        alpha.append(out["opacity"].cpu())
    return torch.stack(rgb), torch.stack(alpha), field_mesh(params, net.cfg.field, grid, mesh_resolution)


def swap(run: Path, data_root: Path, shape_id: str, color_id: str, out: Path, mesh_resolution: int = 128) -> dict:
    """``hypnerf swap``: renders and mesh of A's shape with B's colour, plus its disentanglement figures."""
    net, meta = load_prior(run)
    a, b = instance_number(meta, shape_id), instance_number(meta, color_id)
    result = disentanglement_pair(net, meta, Path(data_root), a, b, mesh_resolution, out=Path(out))
    (Path(out) / "swap.json").write_text(json.dumps(result, indent=2))
    return result


def disentanglement_pair(net: HyperNetwork, meta: dict, data_root: Path, a: int, b: int, mesh_resolution: int, out: Path | None = None) -> dict:
    ids = [inst["id"] for inst in meta["instances"]]
    test_a = load_views(data_root / ids[a], split="test")
    test_b = load_views(data_root / ids[b], split="test")
    gt_mesh = trimesh.load(test_a.mesh_path, force="mesh") if test_a.mesh_path else None
    swapped_rgb, swapped_alpha, swapped_mesh = render_swap(net, swap_codes(net, a, b), test_a, mesh_resolution)
    _, _, own_mesh = render_swap(net, generate(net, a), test_a, mesh_resolution)
    swapped_lab = foreground_lab(swapped_rgb, swapped_alpha)
    lab_a = foreground_lab(test_a.images[..., :3], test_a.images[..., 3])
    lab_b = foreground_lab(test_b.images[..., :3], test_b.images[..., 3])
    result = {
        "shape": ids[a],
        "color": ids[b],
        "chamfer_swapped": mesh_chamfer(swapped_mesh, gt_mesh) if gt_mesh is not None else None,
        "chamfer_own": mesh_chamfer(own_mesh, gt_mesh) if gt_mesh is not None else None,
        "colour_distance_to_color_source": colour_distance(swapped_lab, lab_b),
        "colour_distance_to_shape_source": colour_distance(swapped_lab, lab_a),
        "colour_distance_between_sources": colour_distance(lab_a, lab_b),
    }
    if result["chamfer_swapped"] is not None and result["chamfer_own"]:
        result["chamfer_ratio"] = result["chamfer_swapped"] / result["chamfer_own"]
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        for i, image in enumerate(swapped_rgb):
            save_png(out / f"view_{i:03d}.png", image)
        export_mesh(swapped_mesh, out / "mesh.glb")
    return result


def disentanglement(run: Path, data_root: Path, *, pairs: int = 10, min_colour_distance: float = 20.0, seed: int = 0, mesh_resolution: int = 128) -> dict:
    """Swap the codes of ``pairs`` instance pairs of different shapes and clearly different colours
    (mean foreground colours at least ``min_colour_distance`` apart) and measure both halves."""
    net, meta = load_prior(run)
    data_root = Path(data_root)
    instances = meta["instances"]
    labs = {}
    for n, inst in enumerate(instances):
        test = load_views(data_root / inst["id"], split="test")
        labs[n] = foreground_lab(test.images[..., :3], test.images[..., 3])
    rng = random.Random(seed)
    shapes = spread_instances(meta, pairs)
    rows = []
    for a in tqdm(shapes, desc="disentanglement", unit="pair"):
        candidates = [
            b for b in range(len(instances))
            if instances[b]["shape_index"] != instances[a]["shape_index"] and colour_distance(labs[a], labs[b]) >= min_colour_distance
        ]
        if not candidates:
            continue
        rows.append(disentanglement_pair(net, meta, data_root, a, rng.choice(candidates), mesh_resolution))
    if not rows:
        raise ValueError("no instance pairs of different shapes and clearly different colours; train on more varied data")
    ratios = [r["chamfer_ratio"] for r in rows if r.get("chamfer_ratio") is not None]
    return {
        "pairs": len(rows),
        "chamfer_ratio_mean": statistics.fmean(ratios) if ratios else None,
        "chamfer_ratio_max": max(ratios) if ratios else None,
        "colour_distance_to_color_source_mean": statistics.fmean(r["colour_distance_to_color_source"] for r in rows),
        "colour_distance_to_shape_source_mean": statistics.fmean(r["colour_distance_to_shape_source"] for r in rows),
        "colour_closer_to_color_source": sum(r["colour_distance_to_color_source"] < r["colour_distance_to_shape_source"] for r in rows),
        "colour_metric": "CIE76 Delta E between mean CIELAB foreground colours of the held-out views",
        "rows": rows,
        "run": str(run),
    }
