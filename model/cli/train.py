"""``hypnerf train``: the hypernetwork prior on a category (``torchrun ... -m model.cli train`` for
data-parallel training with the same options)."""

from __future__ import annotations

import argparse
from pathlib import Path

from model.data.category import OCCUPANCY_SOURCES
from model.prior.hypernet import PRESET_NAMES, preset
from model.train.prior import TrainConfig, train


def register(parser: argparse.ArgumentParser) -> None:
    defaults = TrainConfig()
    parser.add_argument("--data", required=True, type=Path, help="dataset folder (its train split is used)")
    parser.add_argument("--out", required=True, type=Path, help="run folder: checkpoint, history, exported prior")
    parser.add_argument("--preset", default="cpu", choices=PRESET_NAMES, help="hypernetwork size (default cpu)")
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--objects-per-step", type=int, default=defaults.objects_per_step)
    parser.add_argument("--rays", type=int, default=defaults.rays_per_step, help="rays per step over all objects")
    parser.add_argument("--lr", type=float, default=defaults.lr)
    parser.add_argument("--validate-every", type=int, default=defaults.validate_every, help="steps between validation renders (0: never)")
    parser.add_argument("--checkpoint-every", type=int, default=defaults.checkpoint_every)
    parser.add_argument("--limit", type=int, help="train on the first N instances only")
    parser.add_argument("--occupancy", choices=OCCUPANCY_SOURCES, default=defaults.occupancy,
                        help="where training rays take samples: the visual hull (default), cells at the ground-truth mesh surface, or the whole box")
    parser.add_argument("--code-noise", type=float, default=defaults.code_noise,
                        help="variational codebook: Gaussian noise on the codes during training, in units of the codebook's per-dimension std (default 0: none)")
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint (its settings win)")
    parser.add_argument("--until", type=int, help="stop after this step with a checkpoint (continue later with --resume)")
    parser.set_defaults(func=run)


def run(args) -> int:
    if args.steps < 1:
        raise ValueError("--steps must be at least 1")
    if args.code_noise < 0:
        raise ValueError("--code-noise must be 0 or more (units of the codebook's per-dimension std)")
    tcfg = TrainConfig(
        steps=args.steps,
        objects_per_step=args.objects_per_step,
        rays_per_step=args.rays,
        lr=args.lr,
        validate_every=args.validate_every,
        checkpoint_every=args.checkpoint_every,
        occupancy=args.occupancy,
        code_noise=args.code_noise,
        seed=args.seed,
    )
    summary = train(args.data, args.out, preset(args.preset), tcfg, resume=args.resume, until=args.until, limit=args.limit)
    if summary:
        final = summary.get("final", {})
        print(f"trained {summary['instances']} instances in {summary['wall_s']:.0f} s; final train PSNR {final.get('train_psnr', float('nan')):.2f} dB -> {args.out}")
    return 0
