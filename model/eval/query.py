"""What the query network is worth: retrieval of training instances from unposed views (the paper's
Table 3), with clean and cluttered backgrounds; text-to-NeRF on held-out prompts; interpolation
and unconditional samples (the paper's second limitation).

- Retrieval queries are ground-truth renders of training instances at **new random poses**: the
  project's ray caster (``model.data.raycast``) renders each instance's own mesh (for Sweet Home 3D
  objects the textured source model with the instance's colour variant, rebuilt exactly as the
  dataset was; otherwise the object's ``mesh.ply``) from elevations, distances and focal lengths
  the dataset never used (:class:`NovelPoses`). Three ways of retrieving are scored: Delta's codes
  to the nearest codebook instance (the paper's way), and cosine similarity to a bank of image
  embeddings of the training renders, one per instance (mean of its views) or every view (best
  view per instance). Cluttered queries composite the object over a random procedural background
  (:func:`clutter`), then segment it back with ``model.nerf.segment`` (GrabCut, what a user's photo
  goes through) from the image border alone or from a box around the object (a user's box prompt,
  simulated from the true mask), or embed the composite as it is.
- Text-to-NeRF prompts come from attribute pairs (colour, type) with held-out templates and colour
  words (``model.prior.captions``). The generated NeRF is rendered at three fixed poses; its
  dominant colour is the palette name (``model.data.colours``; nearest in CIELAB up to the
  renderer's shading) covering most foreground pixels, and its type is the type of the training shape nearest its shape code. The same colour
  measurement on the ground-truth renders of training instances (against their captions) is
  reported beside it: the ceiling the measurement itself allows.
- Sampling: codes drawn from a Gaussian mixture fitted on the codebook (``model.prior.sampling``);
  reported are their distance to the nearest training code (relative to the codebook's own
  spacing), and validity proxies on renders and meshes: foreground fraction, a haze fraction
  (foreground pixels with opacity between 0.05 and 0.95: a cross-faded or hazy NeRF has many) and
  the share of watertight meshes, each beside the same figures for training codes.
"""

from __future__ import annotations

import logging
import math
import random
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw
from tqdm import tqdm

from model.data.build import RenderSettings
from model.data.cameras import RADIUS, evaluation_poses, look_at, training_poses
from model.data.dataset import TRANSFORMS_FILE, load_index, load_views
from model.data.meshes import RenderMesh, load_mesh_file, normalise
from model.data.raycast import render_views as raycast_views
from model.data.variants import material_variants
from model.nerf.images import composite_over, to_uint8
from model.nerf.mesh import field_mesh
from model.nerf.rays import Intrinsics
from model.nerf.renderer import RenderConfig, render_image
from model.nerf.segment import SegmentationError, object_rgba
from model.prior.captions import COLOUR_SYNONYMS, attributes, held_out_prompt
from model.prior.codes import generated_grid
from model.prior.colour_measure import COLOUR_POSES, dominant_colour_of, render_codes
from model.prior.embedders import embed_queries
from model.prior.embedding_cache import view_embeddings
from model.prior.io import Prior
from model.prior.query import (
    QueryPipeline,
    code_distances,
    instance_bank,
    nearest_instances,
)
from model.prior.sampling import (
    CodeDensity,
    DensityConfig,
    interpolate,
    nearest_code_distance,
)

log = logging.getLogger(__name__)

# the box's bounding sphere: every normalised object lies inside [-0.45, 0.45]^3
OBJECT_RADIUS = 0.45 * math.sqrt(3.0)


# ---------------------------------------------------------------------------------------------
# Query views at new poses


@dataclass
class NovelPoses:
    """Random query cameras: elevation and distance ranges, and how much wider than the object's
    bounding sphere the field of view is (1 = the sphere touches the image border; the focal
    length follows, so near cameras get wide lenses and far ones long lenses)."""

    elevation_deg: tuple[float, float] = (5.0, 70.0)
    radius: tuple[float, float] = (1.5, 3.2)
    fov_margin: tuple[float, float] = (1.0, 1.5)
    target_jitter: float = 0.04

    def sample(self, rng: np.random.Generator, resolution: int) -> tuple[np.ndarray, float]:
        """One camera: ``(c2w [4, 4], focal in pixels)``."""
        elevation = math.radians(rng.uniform(*self.elevation_deg))
        azimuth = rng.uniform(0.0, 2.0 * math.pi)
        radius = rng.uniform(*self.radius)
        direction = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
        target = rng.uniform(-self.target_jitter, self.target_jitter, 3)
        half_fov = min(math.asin(min(OBJECT_RADIUS / radius, 0.99)) * rng.uniform(*self.fov_margin), math.radians(75.0))
        return look_at(target + radius * direction, target), 0.5 * resolution / math.tan(half_fov)


def angle_to_training_views(c2w: np.ndarray, views: int) -> float:
    """Degrees between a camera's viewing direction from the origin and the nearest training pose's."""
    train = training_poses(views)[:, :3, 3]
    train = train / np.linalg.norm(train, axis=1, keepdims=True)
    own = c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
    return float(np.degrees(np.arccos(np.clip(train @ own, -1.0, 1.0).max())))


def shape_meshes(data: Path, entries: list[dict]) -> dict[str, RenderMesh]:
    """The meshes the renders of instances of one shape were made from, by instance id: for Sweet
    Home 3D objects the source model with each instance's colour variant (rebuilt as
    ``model.data.build`` did), else each object's ``mesh.ply``."""
    from model.data.sh3d import PACKAGE, sh3d_objects

    data = Path(data)
    first = entries[0]
    if first.get("source") != PACKAGE:
        for entry in entries:
            if not (data / entry["id"] / "mesh.ply").is_file():
                raise ValueError(f"{data / entry['id']} has no mesh.ply to render new views from")
        return {e["id"]: load_mesh_file(data / e["id"] / "mesh.ply")[0] for e in entries}
    shape_id = first.get("shape_id", first["id"])
    source = next((o for o in sh3d_objects(first["category"]) if o.id == shape_id), None)
    if source is None:
        raise ValueError(f"{shape_id} is not in the installed {PACKAGE} category list; the dataset was built from another version")
    mesh = normalise(source.load()[0])
    variants = material_variants(mesh, RenderSettings(**_render_settings(data / first["id"])).variants, shape_id)
    return {e["id"]: variants[int(e.get("variant", 0))] for e in entries}


def _render_settings(folder: Path) -> dict:
    import json

    return json.loads((folder / TRANSFORMS_FILE).read_text()).get("render", {})


def render_queries(mesh: RenderMesh, poses: list[tuple[np.ndarray, float]], resolution: int) -> torch.Tensor:
    """Ground-truth RGBA ``[Q, R, R, 4]`` in [0, 1] of a mesh from ``(c2w, focal)`` cameras."""
    images = [raycast_views(mesh, c2w[None], resolution, resolution, focal, desc="query views")[0] for c2w, focal in poses]
    return torch.from_numpy(np.stack(images)).float() / 255.0


def clutter(rng: np.random.Generator, size: int) -> np.ndarray:
    """A random cluttered background ``[size, size, 3]`` in [0, 1]: a smooth colour field with
    random rectangles, discs and lines (OpenCV drawing), like a room behind a product."""
    import cv2

    field = rng.uniform(0.0, 1.0, (4, 4, 3)).astype(np.float32)
    canvas = cv2.resize(field, (size, size), interpolation=cv2.INTER_CUBIC)
    for _ in range(int(rng.integers(6, 14))):
        colour = tuple(float(c) for c in rng.uniform(0.0, 1.0, 3))
        x0, y0 = (int(v) for v in rng.integers(0, size, 2))
        kind = rng.integers(0, 3)
        if kind == 0:
            x1, y1 = (int(v) for v in rng.integers(0, size, 2))
            cv2.rectangle(canvas, (x0, y0), (x1, y1), colour, -1)
        elif kind == 1:
            cv2.circle(canvas, (x0, y0), int(rng.integers(3, size // 4)), colour, -1)
        else:
            x1, y1 = (int(v) for v in rng.integers(0, size, 2))
            cv2.line(canvas, (x0, y0), (x1, y1), colour, int(rng.integers(1, 4)))
    return np.clip(canvas, 0.0, 1.0)


def over_background(rgba: torch.Tensor, background: np.ndarray) -> np.ndarray:
    """An RGBA view ``[H, W, 4]`` composited over a background ``[H, W, 3]``: a plain photo."""
    image = rgba.numpy()
    return image[..., :3] * image[..., 3:] + background * (1.0 - image[..., 3:])


# ---------------------------------------------------------------------------------------------
# Retrieval


def ranks_of(scores: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Rank (0 = best) of the true column of each row of ``scores [Q, I]`` (higher is better)."""
    true = scores.gather(1, truth[:, None])
    return (scores > true).sum(dim=1)


def retrieval_scores(pipeline: QueryPipeline, embeddings: torch.Tensor, bank_mean: torch.Tensor, bank_views: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per method, scores ``[Q, I]`` of every instance for image embeddings ``[Q, E]`` (higher is better)."""
    with torch.no_grad():
        shape, color = pipeline.net(pipeline.net.joint(image=embeddings))
        shape_d, color_d = code_distances(pipeline.net, shape, color, pipeline.shape_book, pipeline.color_book)
    normed = torch.nn.functional.normalize(embeddings, dim=-1)
    return {
        "query": -(shape_d + color_d),
        "query_shape": -shape_d,
        "bank_mean": normed @ bank_mean.T,
        "bank_views": torch.einsum("qe,ive->qiv", normed, bank_views).amax(dim=2),
    }


def retrieval_summary(scores: dict[str, torch.Tensor], truth: torch.Tensor, shape_of: torch.Tensor) -> dict:
    """top-1, top-3 and shape-only top-1 of each method."""
    out = {}
    for method in ("query", "bank_mean", "bank_views"):
        ranks = ranks_of(scores[method], truth)
        top = scores[method].argmax(dim=1)
        out[method] = {
            "top1": float((ranks < 1).float().mean()),
            "top3": float((ranks < 3).float().mean()),
            "shape_top1": float((shape_of[top] == shape_of[truth]).float().mean()),
        }
    # Delta's shape code alone: the nearest shape code names the mesh whatever the colour
    out["query"]["shape_top1_from_shape_code"] = float((shape_of[scores["query_shape"].argmax(dim=1)] == shape_of[truth]).float().mean())
    return out


def retrieval(pipeline: QueryPipeline, data: Path, *, views_per_instance: int = 2, seed: int = 0, clutter_queries: bool = True,
              bank_views: int = 24, resolution: int = 128, grid_png: Path | None = None) -> dict:
    """Retrieval of every training instance from ``views_per_instance`` new random views."""
    data = Path(data)
    prior = pipeline.prior
    instances = prior.instances
    entries = {e.id: e.to_json() for e in load_index(data)}
    embedder = pipeline.embedders["image"]
    rng = np.random.default_rng(seed)
    sampler = NovelPoses()
    dataset_views = len(load_views(data / instances[0]["id"], split="train").files)
    clean, cluttered, truth, angles, examples = [], [], [], [], []
    segmented = {"border": [], "box": []}
    ious = {"border": [], "box": []}
    rejected = {"border": 0, "box": 0}
    meshes: dict[str, RenderMesh] = {}
    for n, inst in enumerate(tqdm(instances, desc="retrieval queries", unit="instance")):
        if inst["id"] not in meshes:
            meshes = shape_meshes(data, [entries[i["id"]] for i in instances if i["shape_index"] == inst["shape_index"]])
        poses = [sampler.sample(rng, resolution) for _ in range(views_per_instance)]
        angles += [angle_to_training_views(c2w, dataset_views) for c2w, _ in poses]
        views = render_queries(meshes[inst["id"]], poses, resolution)
        clean.append(embed_queries(embedder, views))
        truth += [n] * len(views)
        if clutter_queries:
            photos = [over_background(v, clutter(rng, resolution)) for v in views]
            cluttered.append(embed_queries(embedder, torch.from_numpy(np.stack(photos)).float()))
            for view, photo in zip(views, photos):
                truth_mask = view[..., 3].numpy() > 0.5
                shown = [composite_over(view), torch.from_numpy(photo).float()]
                for prompt, box in (("border", None), ("box", prompt_box(truth_mask))):
                    try:
                        rgba, _ = object_rgba(photo, box=box)
                    except SegmentationError:
                        rejected[prompt] += 1
                        rgba = np.concatenate([photo, np.ones_like(photo[..., :1])], axis=-1)
                    ious[prompt].append(_iou(rgba[..., 3] > 0.5, truth_mask))
                    segmented[prompt].append(embed_queries(embedder, torch.from_numpy(rgba).float()[None]))
                    shown.append(composite_over(torch.from_numpy(rgba).float()))
                if len(examples) < 6:
                    examples.append(tuple(shown))
    truth_t = torch.tensor(truth)
    shape_of = torch.tensor([inst["shape_index"] for inst in instances])
    ids = [inst["id"] for inst in instances]
    bank_all = torch.stack([view_embeddings(embedder, data / i, "train", bank_views) for i in ids])
    bank_all = torch.nn.functional.normalize(bank_all, dim=-1)
    bank_mean = instance_bank(bank_all)
    conditions = {"clean": torch.cat(clean)}
    if clutter_queries:
        conditions["cluttered_grabcut_box"] = torch.cat(segmented["box"])
        conditions["cluttered_grabcut_border"] = torch.cat(segmented["border"])
        conditions["cluttered_unsegmented"] = torch.cat(cluttered)
    results = {name: retrieval_summary(retrieval_scores(pipeline, emb, bank_mean, bank_all), truth_t, shape_of) for name, emb in conditions.items()}
    if grid_png is not None and examples:
        save_rows(grid_png, examples)
    best = results["clean"]["query"]
    return {
        "top1": best["top1"],
        "top3": best["top3"],
        "shape_top1": best["shape_top1_from_shape_code"],
        "queries": len(truth),
        "instances": len(instances),
        "shapes": int(shape_of.max()) + 1,
        "method": "Delta's codes of the query's image embedding (mean direction with its left-right mirror's) -> nearest codebook instance (standardised code distance)",
        "conditions": results,
        "segmentation": {p: {"mean_iou": statistics.fmean(ious[p]), "rejected": rejected[p]} for p in ious} if ious["box"] else None,
        "box_prompt": f"the object's bounding box grown by {BOX_MARGIN:.0%} of its size per side, as a user would draw it",
        "queries_source": "ground-truth ray-cast renders of each instance's mesh (textured source model and colour variant) at new random poses",
        "poses": {
            "elevation_deg": list(sampler.elevation_deg), "radius": list(sampler.radius), "fov_margin": list(sampler.fov_margin),
            "dataset_radius": RADIUS, "angle_to_nearest_training_view_deg": {"min": min(angles), "median": statistics.median(angles)},
        },
        "bank_views_per_instance": bank_all.shape[1],
        "embedder": embedder.name,
    }


BOX_MARGIN = 0.1


def prompt_box(mask: np.ndarray, margin: float = BOX_MARGIN) -> tuple[int, int, int, int]:
    """A box ``(x0, y0, x1, y1)`` around a mask, grown by ``margin`` of its size on each side."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    dy, dx = margin * (y1 - y0), margin * (x1 - x0)
    return int(x0 - dx), int(y0 - dy), int(np.ceil(x1 + dx)), int(np.ceil(y1 + dy))


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def save_rows(path: Path, rows: list[tuple[torch.Tensor, ...]], labels: list[str] | None = None, label_width: int = 0) -> None:
    """A PNG of image rows (RGB ``[H, W, 3]`` tensors, resized to the first one's size), 2 px white
    gutters, with an optional text label left of each row."""
    size = rows[0][0].shape[:2]
    gutter = 2
    columns = max(len(r) for r in rows)
    height, width = size
    canvas = Image.new("RGB", (label_width + columns * (width + gutter), len(rows) * (height + gutter)), "white")
    draw = ImageDraw.Draw(canvas)
    for r, row in enumerate(rows):
        top = r * (height + gutter)
        if labels:
            _draw_wrapped(draw, labels[r], (4, top + 4), label_width - 8)
        for c, image in enumerate(row):
            tile = Image.fromarray(to_uint8(image)).resize((width, height))
            canvas.paste(tile, (label_width + c * (width + gutter), top))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path)


def _draw_wrapped(draw: ImageDraw.ImageDraw, text: str, origin: tuple[int, int], width: int) -> None:
    words, lines, line = text.split(), [], ""
    for word in words:
        trial = f"{line} {word}".strip()
        if draw.textlength(trial) > width and line:
            lines.append(line)
            line = word
        else:
            line = trial
    lines.append(line)
    draw.multiline_text(origin, "\n".join(lines), fill="black", spacing=2)


# ---------------------------------------------------------------------------------------------
# Text-to-NeRF


# a colour "shows" when it covers at least this share of the foreground: multi-material chairs are
# captioned by the material with the largest surface, which need not be the one most in view
COLOUR_PRESENT_SHARE = 0.25


def prompt_set(entries: list[dict], count: int, seed: int) -> list[dict]:
    """``count`` held-out prompts: three quarters from (colour, type) pairs some training instance
    has, the rest from pairs none has (a type in a colour no instance of that type wears), which
    only a disentangled prior can answer."""
    rng = random.Random(seed)
    seen = sorted({(a.colour, a.kind) for a in map(attributes, entries) if a.colour in COLOUR_SYNONYMS})
    kinds = sorted({kind for _, kind in seen})
    unseen = [(c, k) for c in COLOUR_SYNONYMS for k in kinds if (c, k) not in seen]
    rng.shuffle(seen)
    rng.shuffle(unseen)
    take_unseen = min(len(unseen), count - min(len(seen), math.ceil(0.75 * count)))
    pairs = [(c, k, True) for c, k in seen[: count - take_unseen]] + [(c, k, False) for c, k in unseen[:take_unseen]]
    # every other prompt names its colour with a word no training caption uses
    return [{"prompt": held_out_prompt(c, k, rng, synonym=n % 2 == 1), "colour": c, "type": k, "pair_in_training": s, "colour_synonym": n % 2 == 1}
            for n, (c, k, s) in enumerate(pairs)]


def text_to_nerf(pipeline: QueryPipeline, data: Path, *, prompts: int = 40, seed: int = 0, snap: bool = True, read_colours: bool = True,
                 grid_png: Path | None = None) -> dict:
    """Generate a NeRF per held-out prompt and score its dominant colour and its type; with
    ``read_colours`` the prompt's colour words are read with the colour lexicon first and the
    colour it names constrains the snapped colour code (``QueryPipeline.text_embedding``)."""
    data = Path(data)
    prior = pipeline.prior
    index = {e.id: e.to_json() for e in load_index(data)}
    entries = [index[inst["id"]] for inst in prior.instances]
    kinds = [attributes(e).kind for e in entries]
    camera = Intrinsics.centred(**{k: prior.meta["camera"][k] for k in ("width", "height")}, focal=prior.meta["camera"]["fx"])
    poses = evaluation_poses()[list(COLOUR_POSES)]
    rows, tiles, labels = [], [], []
    for item in tqdm(prompt_set(entries, prompts, seed), desc="text-to-NeRF", unit="prompt"):
        embedding, read = pipeline.text_embedding(item["prompt"], read_colours)
        raw_shape, raw_color = pipeline.codes(embedding, snap=False)
        shape, color = pipeline.codes(embedding, snap=True, colour=read.palette) if snap else (raw_shape, raw_color)
        images, opacity = render_codes(prior, shape, color, poses, camera)
        colour, shares = dominant_colour_of(images, opacity)
        nearest = int(nearest_instances(pipeline.net, raw_shape, raw_color, pipeline.shape_book, pipeline.color_book)[0, 0])
        shape_d, _ = code_distances(pipeline.net, raw_shape, raw_color, pipeline.shape_book, pipeline.color_book)
        kind = kinds[int(shape_d.argmin())]
        rows.append({**item, "measured_colour": colour, "colour_shares": shares, "measured_type": kind,
                     "colour_ok": colour == item["colour"], "colour_present": shares.get(item["colour"], 0.0) >= COLOUR_PRESENT_SHARE,
                     "type_ok": kind == item["type"], "nearest_instance": prior.instances[nearest]["id"],
                     "read_as": read.prompt, "colour_word": read.name, "colour_word_as": read.palette,
                     "colour_code_of": prior.instances[int((pipeline.color_book - color).square().sum(1).argmin())]["id"]})
        tiles.append((images[0], images[1]))
        labels.append(f"{item['prompt']}  ->  {colour}, {kind}")
    ceiling = colour_measure_agreement(data, entries)
    sample_view = load_views(data / prior.instances[0]["id"], split="test").images[0]
    timing = query_timings(pipeline, rows[0]["prompt"], sample_view, camera, evaluation_poses()[0]) if rows else None
    if grid_png is not None:
        save_rows(grid_png, tiles, labels, label_width=260)

    def share(key: str, subset=None, by: str = "pair_in_training") -> float | None:
        chosen = [r for r in rows if subset is None or r[by] == subset]
        return sum(r[key] for r in chosen) / len(chosen) if chosen else None

    def subset(flag: bool, by: str = "pair_in_training") -> dict:
        return {"prompts": sum(r[by] == flag for r in rows), "colour_accuracy": share("colour_ok", flag, by),
                "colour_present": share("colour_present", flag, by), "type_accuracy": share("type_ok", flag, by)}

    return {
        "colour_accuracy": share("colour_ok"),
        "colour_present": share("colour_present"),
        "type_accuracy": share("type_ok"),
        "prompts": len(rows),
        "pairs_in_training": subset(True),
        "pairs_not_in_training": subset(False),
        "palette_colour_words": subset(False, "colour_synonym"),
        "colour_synonyms": subset(True, "colour_synonym"),
        "synonyms_the_lexicon_knows": {"prompts": sum(bool(r["colour_word"]) for r in rows if r["colour_synonym"]),
                                       "read_as_the_prompt_colour": sum(r["colour_word_as"] == r["colour"] for r in rows if r["colour_synonym"])},
        "snapped": snap,
        "colour_words_read": read_colours,
        "colour_measure_on_ground_truth": ceiling,
        "timing_ms": timing,
        "colour_present_metric": f"the prompt's colour covers at least {COLOUR_PRESENT_SHARE:.0%} of the foreground pixels",
        "colour_wearers": "the snapped colour code is the nearest among the instances captioned with the prompt's palette colour and, where any is, dominated by it in renders of their own codes",
        "colour_metric": "palette name covering most foreground pixels (opacity > 0.5) of 3 renders at 40 degrees elevation; a pixel's name is the palette colour nearest in CIELAB after scaling it by the best-matching irradiance of the renderer's shading range",
        "type_metric": "type (from the catalogue name) of the training shape whose code is nearest the predicted shape code",
        "rows": rows,
    }


def query_timings(pipeline: QueryPipeline, prompt: str, image: torch.Tensor, camera: Intrinsics, pose: np.ndarray, repeats: int = 5) -> dict:
    """Median milliseconds of each stage of a query (after one warm-up): text and image embedding,
    Delta (with snapping), the hypernetwork, the occupancy grid and the first render."""
    prior = pipeline.prior
    stages: dict[str, list[float]] = {}

    def timed(name, fn):
        begin = time.perf_counter()
        value = fn()
        stages.setdefault(name, []).append(1000 * (time.perf_counter() - begin))
        return value

    for _ in range(repeats + 1):
        embedding, read = timed("text_embedding", lambda: pipeline.text_embedding(prompt))
        timed("image_embedding", lambda: pipeline.embed(image=image))
        shape, color = timed("query_network", lambda: pipeline.codes(embedding, snap=True, colour=read.palette))
        with torch.no_grad():
            params = timed("hypernetwork", lambda: prior.net.params_from_codes(shape, color))
        grid = timed("occupancy_grid", lambda: generated_grid(params, prior.net.cfg.field, prior.scene))
        timed("first_render", lambda: render_image(params, prior.net.cfg.field, torch.as_tensor(pose).float(), camera, RenderConfig(), scene=prior.scene, grid=grid))
    out = {name: statistics.median(values[1:]) for name, values in stages.items()}
    out["text_to_first_render"] = sum(out[k] for k in ("text_embedding", "query_network", "hypernetwork", "occupancy_grid", "first_render"))
    out["render_resolution"] = f"{camera.width}x{camera.height}"
    out["threads"] = torch.get_num_threads()
    return out


def colour_measure_agreement(data: Path, entries: list[dict], limit: int = 60) -> dict:
    """How often the dominant-colour measurement on an instance's ground-truth views (the same 3
    poses) names its caption's colour: what a perfect text-to-NeRF would score."""
    chosen = [e for e in entries if attributes(e).colour is not None][:limit]
    agree = present = 0
    for entry in chosen:
        views = load_views(Path(data) / entry["id"], split="test").subset(list(COLOUR_POSES))
        colour, shares = dominant_colour_of(composite_over(views.images), views.images[..., 3])
        agree += colour == attributes(entry).colour
        present += shares.get(attributes(entry).colour, 0.0) >= COLOUR_PRESENT_SHARE
    count = max(len(chosen), 1)
    return {"instances": len(chosen), "agreement": agree / count, "present": present / count}


# ---------------------------------------------------------------------------------------------
# Interpolation and sampling


def validity(prior: Prior, shape: torch.Tensor, color: torch.Tensor, pose: np.ndarray, camera: Intrinsics, mesh_resolution: int = 64) -> dict:
    """Render and mesh proxies of a NeRF's validity, with its render ``[H, W, 3]``."""
    with torch.no_grad():
        params = prior.net.params_from_codes(shape, color)
    grid = generated_grid(params, prior.net.cfg.field, prior.scene)
    out = render_image(params, prior.net.cfg.field, torch.as_tensor(pose).float(), camera, RenderConfig(), scene=prior.scene, grid=grid)
    opacity = out["opacity"]
    visible = opacity > 0.05
    mesh = field_mesh(params, prior.net.cfg.field, grid, prior.scene, mesh_resolution)
    return {
        "foreground_fraction": float((opacity > 0.5).float().mean()),
        "haze_fraction": float(((opacity > 0.05) & (opacity < 0.95)).sum() / visible.sum().clamp_min(1)),
        "watertight": bool(len(mesh.faces)) and bool(mesh.is_watertight),
        "mesh_components": len(mesh.split(only_watertight=False)) if len(mesh.faces) else 0,
        "image": out["rgb"],
    }


def _stats(rows: list[dict]) -> dict:
    return {
        "foreground_fraction": statistics.fmean(r["foreground_fraction"] for r in rows),
        "haze_fraction": statistics.fmean(r["haze_fraction"] for r in rows),
        "watertight_share": sum(r["watertight"] for r in rows) / len(rows),
        "mesh_components_median": statistics.median(r["mesh_components"] for r in rows),
    }


def sampling(prior: Prior, *, samples: int = 12, temperature: float = 1.0, seed: int = 0, pairs: int = 3, steps: int = 5,
             grid_png: Path | None = None, interpolation_png: Path | None = None) -> dict:
    """Unconditional samples from the codebook's density, training codes as the reference, and
    interpolation paths (shape alone, colour alone) between instances of different shapes."""
    start = time.perf_counter()
    camera = Intrinsics.centred(**{k: prior.meta["camera"][k] for k in ("width", "height")}, focal=prior.meta["camera"]["fx"])
    pose = evaluation_poses()[COLOUR_POSES[0]]
    with torch.no_grad():
        shape_book, color_book = prior.net.codes(torch.arange(len(prior.instances)))
    shapes = prior.net.shape_codes.weight.detach()
    density = CodeDensity.fit(shapes, color_book, DensityConfig(seed=seed))
    drawn_shape, drawn_color = density.sample(samples, seed=seed, temperature=temperature)
    shape_rel, _ = nearest_code_distance(drawn_shape, shapes)
    color_rel, _ = nearest_code_distance(drawn_color, color_book)
    drawn = [validity(prior, drawn_shape[i : i + 1], drawn_color[i : i + 1], pose, camera) for i in tqdm(range(samples), desc="samples", unit="sample")]
    rng = random.Random(seed)
    reference_ids = rng.sample(range(len(prior.instances)), min(samples, len(prior.instances)))
    reference = [validity(prior, shape_book[i : i + 1], color_book[i : i + 1], pose, camera) for i in reference_ids]
    paths, path_rows, path_labels = [], [], []
    for _ in range(pairs):
        a = rng.randrange(len(prior.instances))
        b = rng.choice([j for j in range(len(prior.instances)) if prior.instances[j]["shape_index"] != prior.instances[a]["shape_index"]])
        shape_path = interpolate(shape_book[a], shape_book[b], steps)
        color_path = interpolate(color_book[a], color_book[b], steps)
        shape_steps = [validity(prior, s[None], color_book[a : a + 1], pose, camera) for s in shape_path]
        color_steps = [validity(prior, shape_book[a : a + 1], c[None], pose, camera) for c in color_path]
        paths.append({"from": prior.instances[a]["id"], "to": prior.instances[b]["id"],
                      "shape_path_haze": [r["haze_fraction"] for r in shape_steps], "shape_path_foreground": [r["foreground_fraction"] for r in shape_steps],
                      "colour_path_haze": [r["haze_fraction"] for r in color_steps]})
        path_rows += [tuple(r["image"] for r in shape_steps), tuple(r["image"] for r in color_steps)]
        path_labels += [f"shape {prior.instances[a]['id'].removeprefix('sh3d-')} -> {prior.instances[b]['id'].removeprefix('sh3d-')}", "colour, same path"]
    if grid_png is not None:
        per_row = 6
        images = [r["image"] for r in drawn]
        save_rows(grid_png, [tuple(images[i : i + per_row]) for i in range(0, len(images), per_row)])
    if interpolation_png is not None and path_rows:
        save_rows(interpolation_png, path_rows, path_labels, label_width=200)
    for r in drawn + reference:
        r.pop("image")
    return {
        "samples": samples,
        "temperature": temperature,
        "density": {"shape_components": len(density.shape.weights), "colour_components": len(density.color.weights), "kind": "diagonal Gaussian mixture, components by BIC"},
        "distance_to_nearest_training_code": {
            "shape_median": float(shape_rel.median()), "colour_median": float(color_rel.median()),
            "unit": "the codebook's median nearest-neighbour spacing",
        },
        "samples_validity": _stats(drawn),
        "training_codes_validity": _stats(reference),
        "interpolation": paths,
        "haze_metric": "share of visible pixels (opacity > 0.05) whose opacity is below 0.95",
        "rows": drawn,
        "wall_s": time.perf_counter() - start,
    }


# ---------------------------------------------------------------------------------------------
# The query's guess as the start of test-time optimisation


TTO_STARTS = ("query", "mean", "nearest")


def tto_starts(pipeline: QueryPipeline, data: Path, *, objects: int = 3, cfg=None, starts: tuple[str, ...] = TTO_STARTS, evaluation_views: int = 12) -> dict:
    """TTO of unseen test objects from one posed view, started from Delta's guess (from that view's
    embedding, not snapped), the mean code, or the nearest codebook instance (TTO's own default):
    PSNR on the input view over time, and on ``evaluation_views`` of the 91 standard views at the end."""
    from dataclasses import replace

    from model.eval.field import render_views
    from model.eval.generalization import test_objects
    from model.eval.metrics import image_quality
    from model.optimize.tto import TTOConfig, invert
    from model.prior.embedding_cache import spread_views

    cfg = cfg or TTOConfig(steps=150, patience=0)
    prior = pipeline.prior
    rows = []
    for object_id in tqdm(test_objects(Path(data), objects), desc="TTO starts", unit="object"):
        inputs = load_views(Path(data) / object_id, "test").subset([0])
        evaluation = load_views(Path(data) / object_id, "train")
        evaluation = evaluation.subset(spread_views(evaluation_views, len(evaluation.files)))
        guess = pipeline.codes(pipeline.embed(image=inputs.images[0]), snap=False)
        record = {"id": object_id, "starts": {}}
        for start in starts:
            run_cfg = replace(cfg, init="nearest" if start == "nearest" else "mean")
            init = (guess[0][0], guess[1][0]) if start == "query" else None
            result = invert(prior.net, prior.scene, inputs.images, inputs.c2w, inputs.cameras, run_cfg, init=init)
            rgb, opacity, _, _ = render_views(result.params, prior.net.cfg.field, evaluation, RenderConfig(), result.grid, prior.scene)
            quality = image_quality(rgb, evaluation.images, opacity)
            record["starts"][start] = {
                "wall_s": result.wall_s, "init": result.init,
                "history": [{"step": h["step"], "psnr": h["psnr"], "elapsed_s": h["elapsed_s"]} for h in result.history if "psnr" in h],
                "held_out_psnr": quality["psnr"],
                "held_out_psnr_fg": quality["psnr_fg"],
                "held_out_floor_psnr": quality["floor_psnr"],
                "held_out_floor_psnr_fg": quality["floor_psnr_fg"],
            }
        finals = [max(h["psnr"] for h in s["history"]) for s in record["starts"].values()]
        record["target_input_psnr"] = min(finals)
        for s in record["starts"].values():
            s["time_to_target_s"] = next((h["elapsed_s"] for h in s["history"] if h["psnr"] >= record["target_input_psnr"] - 1e-9), None)
            s["first_input_psnr"] = s["history"][0]["psnr"] if s["history"] else None
        rows.append(record)

    def mean(start: str, key: str) -> float:
        return statistics.fmean(r["starts"][start][key] for r in rows if r["starts"][start][key] is not None)

    return {
        "objects": len(rows),
        "steps": cfg.steps,
        "summary": {s: {k: mean(s, k) for k in ("first_input_psnr", "time_to_target_s", "held_out_psnr", "held_out_psnr_fg",
                                                 "held_out_floor_psnr", "held_out_floor_psnr_fg", "wall_s")} for s in starts},
        "target": "per object, the lowest best input-view PSNR any start reached; time_to_target_s is when each start first reached it",
        "rows": rows,
    }
