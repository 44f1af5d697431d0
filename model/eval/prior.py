"""What a trained prior is worth: compression against per-object fits (paper Table 2 and the
ablation of Table 4), storage, and shape/colour disentanglement (paper section 4.5).

Every generated NeRF is judged as the service would use it: the hypernetwork runs once on the
instance's codes, the occupancy grid comes from the NeRF's own density, and the renderer's fast
settings draw the fixed held-out views. Quality is full-image and foreground PSNR beside the
blank-image floor (``model.eval.metrics.image_quality``). Per-object fits of the same field
architecture are the reference (``hypnerf fit``; cached in a folder and reused only when their
settings and data match and their metrics were made by the same fit and evaluation code).

Disentanglement: the density of a NeRF depends on the shape code alone, so a swapped NeRF's
geometry *is* the shape source's, by construction; the report says so and checks it, and measures
what can vary, the colour transfer. Colours are compared in CIELAB (scikit-image's ``rgb2lab``)
pixel by pixel: each foreground pixel of the swap is matched to the nearest colour among the
colour source's foreground pixels (``scipy.spatial.cKDTree``), and the reverse, a Chamfer distance
between colour sets in Delta E (CIE76) that a mean colour would hide.
"""

from __future__ import annotations

import json
import logging
import random
import statistics
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from scipy.spatial import cKDTree
from skimage.color import rgb2lab
from tqdm import tqdm

from model.data.dataset import Views, load_views
from model.eval.field import evaluate_field, evaluation_code_version, fit_and_evaluate, render_views
from model.eval.storage import crossover_instances, storage_curve, storage_model
from model.nerf import config
from model.nerf.fields import FieldParams
from model.nerf.images import composite_over, save_png, to_uint8
from model.nerf.mesh import export_mesh, field_mesh
from model.nerf.renderer import RenderConfig
from model.optimize.fit import FitConfig
from model.prior.codes import generate, generated_grid, swap_codes
from model.prior.io import PRIOR_WEIGHTS, Prior, load_prior

log = logging.getLogger(__name__)

QUALITY_KEYS = ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg", "ssim", "chamfer", "render_ms", "samples_per_ray")


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


def _summary(rows: list[dict]) -> dict:
    out = {}
    for key in QUALITY_KEYS:
        values = [r[key] for r in rows if r.get(key) is not None]
        out[key] = statistics.fmean(values) if values else None
    return out


def evaluate_generated(prior: Prior, params: FieldParams, test_views: Views, mesh_resolution: int):
    grid = generated_grid(params, prior.net.cfg.field, prior.scene)
    metrics, renders, mesh = evaluate_field(params, prior.net.cfg.field, grid, test_views, RenderConfig(), scene=prior.scene, mesh_resolution=mesh_resolution)
    metrics["occupied_fraction"] = grid.fraction
    return metrics, renders, mesh


def per_object_fit(root: Path, object_id: str, fits: Path, cfg: FitConfig, device, mesh_resolution: int) -> tuple[dict, int]:
    """Metrics and checkpoint bytes of a per-object fit, reusing one in ``fits`` made with the same
    settings and data by the same code version."""
    out = fits / object_id
    metrics_file, config_file = out / "metrics.json", out / "config.json"
    if metrics_file.is_file() and config_file.is_file():
        saved, metrics = json.loads(config_file.read_text()), json.loads(metrics_file.read_text())
        same = (
            metrics.get("code_version") == evaluation_code_version()
            and config.from_dict(FitConfig, saved["fit"]) == cfg
            and Path(saved.get("data", "")) == root.resolve()
        )
        if same:
            log.info("reusing the per-object fit of %s in %s", object_id, out)
            return metrics, (out / "field.safetensors").stat().st_size
        log.info("the per-object fit in %s was made with other settings or code; fitting again", out)
    metrics = fit_and_evaluate(root, object_id, out, cfg, device, mesh_resolution)
    return metrics, (out / "field.safetensors").stat().st_size


def prior_storage(prior: Prior, fit_cfg: FitConfig, weights_file: Path) -> dict:
    """Storage of this prior against fits at its own precision and its own code sharing, with the
    curve of bytes against the number of instances (computed from parameter counts)."""
    net = prior.net
    counts = net.head_parameter_counts()
    heads = sum(v for k, v in counts.items() if not k.endswith("codebook"))
    itemsize = torch.empty((), dtype=getattr(torch, prior.meta.get("weights_dtype", "float32"))).element_size()
    model = storage_model(net.cfg, heads, fit_cfg.field, itemsize)
    instances = len(prior.instances)
    shapes = net.shape_codes.num_embeddings
    variants = instances / shapes
    here = storage_curve(model, [instances], variants)[0]
    counts_axis = sorted({1, 10, 50, 100, instances, 500, 1000, 2000, 5000, 10000})
    return {
        "weights_dtype": prior.meta.get("weights_dtype", "float32"),
        "instances": instances,
        "shapes": shapes,
        "prior_file_bytes": weights_file.stat().st_size,
        "prior_bytes": here["prior_bytes"],
        "fits_shared_bytes": here["fits_shared_bytes"],
        "fits_unshared_bytes": here["fits_unshared_bytes"],
        "ratio_fits_shared_to_prior": here["fits_shared_bytes"] / here["prior_bytes"],
        "crossover_instances": crossover_instances(model, variants),
        "per_item": model,
        "curve": storage_curve(model, counts_axis, variants),
        "method": "parameter counts x bytes per value at the prior's precision; fits share geometry per mesh as the prior shares shape codes",
    }


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
    prior = load_prior(run, device)
    field_kind = prior.net.cfg.field.kind
    if ablation == "no-mrhe" and field_kind == "hashgrid":
        raise ValueError(f"{run} is a hash-grid prior; the no-mrhe ablation needs a run trained with --preset cpu-no-mrhe")
    if ablation is None and field_kind != "hashgrid":
        raise ValueError(f"{run} emits a {field_kind} field; evaluate it with --ablation no-mrhe")
    fit_cfg = FitConfig() if field_kind != "hashgrid" else FitConfig(field=prior.net.cfg.field)
    if fit_steps:
        fit_cfg.steps = fit_steps
    fits = Path(fits) if fits else Path(run) / "per-object-fits"
    rows = []
    for n in tqdm(spread_instances(prior.meta, objects), desc="compression", unit="object"):
        object_id = prior.instances[n]["id"]
        test = load_views(Path(data_root) / object_id, split="test")
        generated, _, _ = evaluate_generated(prior, generate(prior.net, n), test, mesh_resolution)
        reference, _ = per_object_fit(Path(data_root), object_id, fits, fit_cfg, device, mesh_resolution)
        rows.append({"object": object_id, "hypernet": _pick(generated), "per_object": _pick(reference)})
        log.info(
            "%s: hypernet %.2f / %.2f dB (full / foreground), per-object %.2f / %.2f dB, floor %.2f / %.2f dB",
            object_id, generated["psnr"], generated["psnr_fg"], reference["psnr"], reference["psnr_fg"], generated["floor_psnr"], generated["floor_psnr_fg"],
        )
    hyper = _summary([r["hypernet"] for r in rows])
    single = _summary([r["per_object"] for r in rows])
    return {
        "hypernet": hyper,
        "per_object": single,
        "objects": len(rows),
        "psnr_gap_db": single["psnr"] - hyper["psnr"],
        "psnr_fg_gap_db": single["psnr_fg"] - hyper["psnr_fg"],
        "foreground": "pixels where the ground-truth alpha > 0 or the rendered opacity >= 1/255; floors are a blank white image on the same pixels",
        "field": field_kind,
        "per_object_field": fit_cfg.field.kind,
        "per_object_steps": fit_cfg.steps,
        "storage": prior_storage(prior, fit_cfg, Path(run) / PRIOR_WEIGHTS),
        "rows": rows,
        "run": str(run),
        "data": str(data_root),
    }


def _pick(metrics: dict) -> dict:
    return {k: metrics.get(k) for k in QUALITY_KEYS}


# ---------------------------------------------------------------------------------------------
# Disentanglement


def foreground_lab(images: torch.Tensor, alpha: torch.Tensor, limit: int = 20000, seed: int = 0) -> np.ndarray:
    """CIELAB colours ``[N, 3]`` of pixels with ``alpha > 0.5`` (at most ``limit``, drawn with a
    fixed seed); ``images [V, H, W, 3]`` in [0, 1]."""
    mask = (alpha > 0.5).cpu().numpy()
    pixels = images.clamp(0, 1).cpu().numpy()[mask].astype(np.float64)
    if len(pixels) > limit:
        pixels = pixels[np.random.default_rng(seed).choice(len(pixels), limit, replace=False)]
    return rgb2lab(pixels[None])[0] if len(pixels) else np.zeros((0, 3))


def colour_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric per-pixel colour distance (Delta E, CIE76) between two sets of Lab colours: the
    mean distance from each colour to the nearest of the other set, averaged over both directions."""
    if len(a) == 0 or len(b) == 0:
        return float("nan")
    return float(0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()))


def mean_colour_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Delta E between the mean Lab colours of two sets."""
    return float(np.linalg.norm(a.mean(axis=0) - b.mean(axis=0))) if len(a) and len(b) else float("nan")


@torch.no_grad()
def geometry_difference(prior: Prior, swapped: FieldParams, shape_params: FieldParams, points: int = 4096) -> float:
    """Largest density difference between two NeRFs at random points: 0 when the geometry is shared."""
    unit = torch.rand(1, points, 3, generator=torch.Generator().manual_seed(0)).to(prior.device)
    field = prior.net.cfg.field
    return float((field.density(swapped, unit)[0] - field.density(shape_params, unit)[0]).abs().max())


def _renders(prior: Prior, params: FieldParams, views: Views):
    """Renders ``[V, H, W, 3]``, opacities ``[V, H, W]`` and the generated grid they used."""
    grid = generated_grid(params, prior.net.cfg.field, prior.scene)
    rgb, alpha, _, _ = render_views(params, prior.net.cfg.field, views, RenderConfig(), grid, prior.scene)
    return rgb.cpu(), alpha.cpu(), grid


def disentanglement_pair(prior: Prior, data_root: Path, a: int, b: int, *, out: Path | None = None, mesh_resolution: int = 128) -> dict:
    """Swap A's shape with B's colour and score the colour transfer; renders (and a mesh) into ``out``."""
    ids = [inst["id"] for inst in prior.instances]
    test_a = load_views(data_root / ids[a], split="test")
    test_b = load_views(data_root / ids[b], split="test")
    swapped = swap_codes(prior.net, a, b)
    swap_rgb, swap_alpha, swap_grid = _renders(prior, swapped, test_a)
    own_b_rgb, own_b_alpha, _ = _renders(prior, generate(prior.net, b), test_b)
    lab_swap = foreground_lab(swap_rgb, swap_alpha)
    lab_a = foreground_lab(test_a.images[..., :3], test_a.images[..., 3])
    lab_b = foreground_lab(test_b.images[..., :3], test_b.images[..., 3])
    lab_own_b = foreground_lab(own_b_rgb, own_b_alpha)
    result = {
        "shape": ids[a],
        "color": ids[b],
        "geometry_max_density_difference": geometry_difference(prior, swapped, generate(prior.net, a)),
        "colour_error_to_color_source": colour_chamfer(lab_swap, lab_b),
        "colour_error_to_shape_source": colour_chamfer(lab_swap, lab_a),
        "colour_error_own_reconstruction_of_color_source": colour_chamfer(lab_own_b, lab_b),
        "mean_colour_distance_to_color_source": mean_colour_distance(lab_swap, lab_b),
        "mean_colour_distance_to_shape_source": mean_colour_distance(lab_swap, lab_a),
        "colour_distance_between_sources": colour_chamfer(lab_a, lab_b),
    }
    result["passed"] = result["colour_error_to_color_source"] < result["colour_error_to_shape_source"]
    result["images"] = (composite_over(test_a.images[0]), composite_over(test_b.images[0]), swap_rgb[0])
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        for i, image in enumerate(swap_rgb):
            save_png(out / f"view_{i:03d}.png", image)
        export_mesh(field_mesh(swapped, prior.net.cfg.field, swap_grid, prior.scene, mesh_resolution), out / "mesh.glb")
    return result


def swap(run: Path, data_root: Path, shape_id: str, color_id: str, out: Path, mesh_resolution: int = 128) -> dict:
    """``hypnerf swap``: renders and mesh of A's shape with B's colour, plus its colour-transfer figures."""
    prior = load_prior(run)
    a, b = prior.instance_number(shape_id), prior.instance_number(color_id)
    result = disentanglement_pair(prior, Path(data_root), a, b, out=Path(out), mesh_resolution=mesh_resolution)
    result.pop("images")
    (Path(out) / "swap.json").write_text(json.dumps(result, indent=2))
    return result


def save_grid(path: Path, rows: list[tuple[torch.Tensor, ...]]) -> None:
    """A PNG of image rows (e.g. shape source, colour source, swap), 2 px white gutters."""
    arrays = [[to_uint8(image) for image in row] for row in rows]
    h, w = arrays[0][0].shape[:2]
    gutter = 2
    canvas = np.full((len(arrays) * (h + gutter), max(map(len, arrays)) * (w + gutter), 3), 255, dtype=np.uint8)
    for r, row in enumerate(arrays):
        for c, image in enumerate(row):
            canvas[r * (h + gutter) : r * (h + gutter) + h, c * (w + gutter) : c * (w + gutter) + w] = image
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(canvas).save(path)


def disentanglement(run: Path, data_root: Path, *, pairs: int = 10, min_colour_distance: float = 20.0, seed: int = 0, grid_png: Path | None = None) -> dict:
    """Swap the codes of ``pairs`` instance pairs of different shapes and clearly different colours
    (mean foreground colours at least ``min_colour_distance`` apart) and score the colour transfer."""
    prior = load_prior(run)
    data_root = Path(data_root)
    instances = prior.instances
    labs = {}
    for n, inst in enumerate(instances):
        test = load_views(data_root / inst["id"], split="test")
        labs[n] = foreground_lab(test.images[..., :3], test.images[..., 3], limit=2000)
    rng = random.Random(seed)
    rows = []
    for a in tqdm(spread_instances(prior.meta, pairs), desc="disentanglement", unit="pair"):
        candidates = [
            b for b in range(len(instances))
            if instances[b]["shape_index"] != instances[a]["shape_index"] and mean_colour_distance(labs[a], labs[b]) >= min_colour_distance
        ]
        if candidates:
            rows.append(disentanglement_pair(prior, data_root, a, rng.choice(candidates)))
    if not rows:
        raise ValueError("no instance pairs of different shapes and clearly different colours; train on more varied data")
    if grid_png is not None:
        save_grid(Path(grid_png), [row["images"] for row in rows])
    for row in rows:
        row.pop("images")

    def mean(key: str) -> float:
        return statistics.fmean(r[key] for r in rows)

    return {
        "pairs": len(rows),
        "geometry": "identical to the shape source's by construction (density depends on the shape code only); "
        "checked on 4096 random points per pair",
        "geometry_max_density_difference": max(r["geometry_max_density_difference"] for r in rows),
        "colour_error_to_color_source_mean": mean("colour_error_to_color_source"),
        "colour_error_to_shape_source_mean": mean("colour_error_to_shape_source"),
        "colour_error_own_reconstruction_mean": mean("colour_error_own_reconstruction_of_color_source"),
        "mean_colour_distance_to_color_source_mean": mean("mean_colour_distance_to_color_source"),
        "mean_colour_distance_to_shape_source_mean": mean("mean_colour_distance_to_shape_source"),
        "passed": sum(r["passed"] for r in rows),
        "pass_fraction": sum(r["passed"] for r in rows) / len(rows),
        "pass_rule": "the swap's per-pixel colour error to the colour source is below its error to the shape source",
        "colour_metric": "symmetric nearest-colour distance between foreground pixel sets in CIELAB (Delta E, CIE76) over the held-out views",
        "grid_png": str(grid_png) if grid_png else None,
        "rows": rows,
        "run": str(run),
    }
