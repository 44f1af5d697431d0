"""Denoisers compared on a development set: deformed copies of training meshes.

The choice of the shipped denoiser must not be made on the test split, and the validation chairs
are in the shipped denoiser's own TTO pairs, so candidates are compared on deformed copies of the
training meshes (``data/sh3d-chair-augmented``, built with ``hypnerf data import-sh3d --augment``;
shapes the prior never saw, in no candidate's pairs; the denoiser trained on TTO of deformed
copies is left out). Candidates missing from ``runs/denoise`` are trained first. Each object is inverted once from its first view (single-view TTO, cached under
``runs/denoise/dev-tto``); every candidate then denoises renders of that NeRF at every third other
view (the denoised image) and runs denoise-and-finetune (the finetuned NeRF at the same views,
the input photo among the finetune views at the default share); the shipped denoiser also at
other shares, and a control finetuned on the input photo alone.
Writes ``benchmarks/results/denoiser_selection.json``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from safetensors.torch import load_file, save_file
from tqdm import tqdm

from benchmarks.bench_denoise import DATA, RUN, quality
from benchmarks.common import ROOT, hypnerf, write_result

DEVELOPMENT = ROOT / "data" / "sh3d-chair-augmented"
TTO_CACHE = ROOT / "runs" / "denoise" / "dev-tto"
# folder under runs/denoise -> (what it is, the `hypnerf train-denoiser` arguments beside --run, --data and --out)
CANDIDATES = {
    "denoiser-tto": ("prior renders + TTO of 12 validation chairs, 3000 steps (shipped)",
                     "--steps 3000 --instances 0 --tto-objects 12 --tto-views 24"),
    "denoiser-tto-long": ("the same pairs, 6000 steps", "--steps 6000 --instances 0 --tto-objects 12 --tto-views 24"),
    "denoiser-tto-share": ("the same pairs, 6000 steps, half of each batch TTO pairs",
                           "--steps 6000 --instances 0 --tto-objects 12 --tto-views 24 --tto-share 0.5"),
    "denoiser": ("prior renders alone (the paper's pairs), 3000 steps", "--steps 3000 --instances 0"),
    "denoiser-tto-inputs3": ("prior renders + TTO of 12 validation chairs from 3 test views each, 3000 steps",
                             "--steps 3000 --instances 0 --tto-objects 12 --tto-views 24 --tto-inputs 3"),
}


def train_command(name: str) -> str:
    """The ``hypnerf train-denoiser`` command line that makes the candidate ``name`` (paths from the checkout)."""
    return f"hypnerf train-denoiser --run {RUN.relative_to(ROOT)} --data {DATA.relative_to(ROOT)} --out runs/denoise/{name} " + CANDIDATES[name][1]


def ensure_candidate(name: str) -> Path:
    """The candidate's folder, trained first (one thread) when it holds no denoiser."""
    folder = ROOT / "runs" / "denoise" / name
    if not (folder / "denoiser.json").is_file():
        hypnerf("train-denoiser", "--run", str(RUN), "--data", str(DATA), "--out", str(folder), *CANDIDATES[name][1].split(),
                *(["--resume"] if (folder / "checkpoint" / "state.json").is_file() else []))
    return folder


SHIPPED = "denoiser-tto"
# further shares of the input photo among the finetune views, tried with the shipped denoiser
# (candidates use the default share, DenoiseConfig.input_share)
INPUT_SHARES = (0.0, 0.2)


FIRST_OBJECTS = 4  # the development set the denoiser, the input share and the rounds were first chosen on


def development_objects(prior, count: int) -> list[str]:
    """``count`` deformed copies (ids with ``-aug``) the prior never saw, spread over them in id
    order; beyond ``FIRST_OBJECTS``, those first ones and then others spread over the rest, so a
    larger development set holds the first."""
    from model.data.dataset import load_index
    from model.train.denoiser import spread

    seen = {inst["id"] for inst in prior.instances}
    ids = sorted(e.id for e in load_index(DEVELOPMENT) if e.split == "train" and e.id not in seen and "-aug" in e.id)
    first = [ids[k] for k in spread(2 * min(count, FIRST_OBJECTS), len(ids))][1::2]
    if count <= FIRST_OBJECTS:
        return first
    rest = [i for i in ids if i not in first]
    return first + [rest[k] for k in spread(2 * (count - FIRST_OBJECTS), len(rest))][1::2]


def development_object(prior, object_id: str):
    """``(inputs, evaluation, params, grid)``: the object's input view (its first), its evaluation
    views (every third after it) and its single-view TTO NeRF (batch 1, inverted once and cached
    under ``TTO_CACHE``) with that NeRF's occupancy grid."""
    from model.data.dataset import load_views
    from model.optimize.tto import TTOConfig, invert
    from model.prior.codes import generated_grid

    views = load_views(DEVELOPMENT / object_id, None)
    inputs, evaluation = views.subset([0]), views.subset(list(range(1, len(views.files), 3)))
    cached = TTO_CACHE / f"{object_id}.safetensors"
    if not cached.is_file():
        TTO_CACHE.mkdir(parents=True, exist_ok=True)
        result = invert(prior.net, prior.scene, inputs.images, inputs.c2w, inputs.cameras, TTOConfig())
        save_file({k: v.contiguous() for k, v in result.params.items()}, str(cached))
    params = load_file(str(cached))
    return inputs, evaluation, params, generated_grid(params, prior.net.cfg.field, prior.scene)


def scored(prior, params, grid, evaluation) -> dict:
    """:func:`benchmarks.bench_denoise.quality` of the NeRF ``params`` (with ``grid``) rendered at ``evaluation``'s views."""
    from model.eval.field import render_views
    from model.nerf.renderer import RenderConfig

    rgb, opacity, _, _ = render_views(params, prior.net.cfg.field, evaluation, RenderConfig(), grid, prior.scene)
    return quality(rgb, evaluation.images, opacity)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=4, help="deformed copies inverted")
    parser.add_argument("--candidates", nargs="*", default=list(CANDIDATES), choices=list(CANDIDATES), help="denoisers compared (trained when missing)")
    args = parser.parse_args(argv)
    from model.denoise.finetune import (
        DenoiseConfig,
        denoise_and_finetune,
        finetune_on_views,
        ring_poses,
    )
    from model.denoise.io import load_denoiser
    from model.denoise.vqvae import denoise_renders
    from model.eval.field import render_views
    from model.nerf import config
    from model.nerf.images import composite_over
    from model.nerf.rays import Intrinsics
    from model.nerf.renderer import RenderConfig
    from model.prior.codes import generated_grid
    from model.prior.io import load_prior

    if not (DEVELOPMENT / "index.json").is_file():
        print(f"{DEVELOPMENT} is missing: `python -m benchmarks.bench_shapes` builds it", file=sys.stderr)
        return 1
    denoisers = {name: load_denoiser(ensure_candidate(name))[0] for name in args.candidates}
    prior = load_prior(RUN)
    field, camera = prior.net.cfg.field, config.from_dict(Intrinsics, prior.meta["camera"])
    objects = development_objects(prior, args.objects)
    rows = {}
    for object_id in tqdm(objects, desc="development objects", unit="object"):
        inputs, evaluation, params, grid = development_object(prior, object_id)
        # the TTO render is kept: each candidate denoises it
        rgb, opacity, _, _ = render_views(params, field, evaluation, RenderConfig(), grid, prior.scene)
        row = {"tto": quality(rgb, evaluation.images, opacity)}
        photo = (inputs.images, inputs.c2w, inputs.cameras)

        for name, denoiser in denoisers.items():
            rgba = denoise_renders(denoiser, rgb, opacity)
            shares = (DenoiseConfig().input_share, *INPUT_SHARES) if name == SHIPPED else (DenoiseConfig().input_share,)
            results = {share: denoise_and_finetune(params, field, prior.scene, denoiser, ring_poses(), camera, DenoiseConfig(input_share=share),
                                                   grid=grid, inputs=photo) for share in shares}
            row[name] = {"denoised_image": quality(composite_over(rgba), evaluation.images, rgba[..., 3]),
                         "denoise_finetune": scored(prior, results[shares[0]].params, results[shares[0]].grid, evaluation)}
            for share in shares[1:]:
                row[f"{name} input share {share:g}"] = {"denoise_finetune": scored(prior, results[share].params, results[share].grid, evaluation)}
        # the control: the same finetune on the input photo alone, no denoised views
        alone = finetune_on_views(params, field, prior.scene, *photo, DenoiseConfig().finetune, grid=grid)
        row["input photo alone"] = {"denoise_finetune": scored(prior, alone, generated_grid(alone, field, prior.scene), evaluation)}
        rows[object_id] = row
        print(f"  {object_id}: TTO {row['tto']['psnr']:.2f} / {row['tto']['psnr_fg']:.2f} dB; "
              + "; ".join(f"{n} {row[n]['denoise_finetune']['psnr']:.2f} / {row[n]['denoise_finetune']['psnr_fg']:.2f}" for n in denoisers), flush=True)

    def mean(get) -> dict:
        return {k: sum(get(r)[k] for r in rows.values()) / len(rows) for k in ("psnr", "psnr_fg", "psnr_fg_gt_mask")}

    first = next(iter(rows.values()))
    summary = {"tto": mean(lambda r: r["tto"]),
               **{name: {stage: mean(lambda r, n=name, s=stage: r[n][s]) for stage in first[name]} for name in first if name != "tto"}}
    for name in (n for n in summary if n != "tto"):
        print(f"{name}: denoise-and-finetune {summary[name]['denoise_finetune']['psnr_fg'] - summary['tto']['psnr_fg']:+.2f} dB foreground over TTO")
    write_result("denoiser_selection", {
        "command": "python -m benchmarks.bench_denoiser_selection " + " ".join(sys.argv[1:] if argv is None else argv),
        "data": str(DEVELOPMENT.relative_to(ROOT)), "prior_data": str(DATA.relative_to(ROOT)), "objects": objects,
        "candidates": {name: CANDIDATES[name][0] for name in denoisers},
        "input_share": DenoiseConfig().input_share, "rounds": DenoiseConfig().rounds, "mirror_inputs": DenoiseConfig().mirror_inputs,
        "variants": {**{f"{SHIPPED} input share {share:g}": f"the shipped denoiser, the input photo {share:.0%} of the finetune views"
                        for share in INPUT_SHARES if SHIPPED in denoisers},
                     "input photo alone": "the same finetune on the input photo alone (no denoised views): the control"},
        "train_commands": {name: train_command(name) for name in denoisers},
        "evaluated_at": "every third view after the input (views 1, 4, 7, ...)", "mean": summary, "rows": rows,
    })
    return 0


if __name__ == "__main__":
    sys.exit(main())
