"""``hypnerf train-denoiser``: the image-to-image denoiser of denoise-and-finetune, trained on
renders of a prior (``model.train.denoiser``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from model.train.denoiser import DenoiserTrainConfig, PairsConfig, train_denoiser


def register(parser: argparse.ArgumentParser) -> None:
    defaults, pair_defaults = DenoiserTrainConfig(), PairsConfig()
    parser.add_argument("--run", required=True, type=Path, help="run folder of the trained prior (prior.json + hypernet.safetensors)")
    parser.add_argument("--data", required=True, type=Path, help="the dataset the prior was trained on")
    parser.add_argument("--out", required=True, type=Path, help="folder for the denoiser (denoiser.safetensors + denoiser.json), its render cache and checkpoint")
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--batch", type=int, default=defaults.batch, help="crops per step")
    parser.add_argument("--crop", type=int, default=defaults.crop, help="side of the training crops in pixels (0: whole images)")
    parser.add_argument("--lr", type=float, default=defaults.lr)
    parser.add_argument("--instances", type=int, default=pair_defaults.instances, help="training instances rendered, spread over the codebook (0: all)")
    parser.add_argument("--clean-views", type=int, default=pair_defaults.clean_views, help="training views rendered per instance from its own codes")
    parser.add_argument("--perturbed-nerfs", type=int, default=pair_defaults.perturbed_nerfs, help="NeRFs of perturbed codes per instance")
    parser.add_argument("--perturbed-views", type=int, default=pair_defaults.perturbed_views, help="views rendered from each perturbed NeRF")
    parser.add_argument("--tto-objects", type=int, default=pair_defaults.tto_objects,
                        help="objects the prior never saw (outside the test split) inverted by single-view TTO, their renders paired with their ground truth")
    parser.add_argument("--tto-data", default=pair_defaults.tto_data,
                        help="the dataset of the TTO objects, e.g. one made with --augment (default: --data)")
    parser.add_argument("--tto-views", type=int, default=pair_defaults.tto_views, help="training views rendered per TTO object")
    parser.add_argument("--tto-inputs", type=int, default=pair_defaults.tto_inputs,
                        help="single-view TTOs per TTO object, each from another of its test views")
    parser.add_argument("--tto-share", type=float, default=defaults.tto_share,
                        help="chance that a batch element is a TTO pair, in [0, 1] (default 0: all pairs equally likely)")
    parser.add_argument("--validate-every", type=int, default=defaults.validate_every, help="steps between validations (0: never)")
    parser.add_argument("--checkpoint-every", type=int, default=defaults.checkpoint_every)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint (its settings win)")
    parser.add_argument("--until", type=int, help="stop after this step with a checkpoint (continue later with --resume)")
    parser.set_defaults(func=run)


def run(args) -> int:
    for name in ("steps", "batch", "checkpoint_every"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be at least 1")
    for name in ("crop", "instances", "clean_views", "perturbed_nerfs", "perturbed_views", "tto_objects", "tto_views", "validate_every"):
        if getattr(args, name) < 0:
            raise ValueError(f"--{name.replace('_', '-')} must not be negative")
    if args.tto_inputs < 1:
        raise ValueError("--tto-inputs must be at least 1 (the TTOs of each TTO object)")
    pairs = PairsConfig(instances=args.instances, clean_views=args.clean_views, perturbed_nerfs=args.perturbed_nerfs, perturbed_views=args.perturbed_views,
                        tto_objects=args.tto_objects, tto_views=args.tto_views, tto_inputs=args.tto_inputs,
                        tto_data=str(args.tto_data or ""), seed=args.seed)
    cfg = DenoiserTrainConfig(
        pairs=pairs, steps=args.steps, batch=args.batch, crop=args.crop, lr=args.lr, tto_share=args.tto_share,
        validate_every=args.validate_every, checkpoint_every=args.checkpoint_every, seed=args.seed,
    )
    summary = train_denoiser(args.run, args.data, args.out, cfg, resume=args.resume, until=args.until)
    if summary:
        final = summary["final"]
        scores = (f"; held-out views {final['val_raw_psnr']:.2f} -> {final['val_psnr']:.2f} dB full, "
                  f"{final['val_raw_psnr_fg']:.2f} -> {final['val_psnr_fg']:.2f} dB foreground") if "val_psnr" in final else ""
        print(f"trained the denoiser for {summary['steps']} steps on {summary['pairs']} pairs in {summary['wall_s']:.0f} s{scores} -> {args.out}")
    return 0
