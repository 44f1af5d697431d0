"""Rounds of denoise-and-finetune on the development set (deformed copies of training meshes).

Each round renders the ring poses of the NeRF the round before finetuned, denoises them with the
shipped denoiser (or another of ``bench_denoiser_selection``'s candidates, ``--denoiser``) and
finetunes on them and the input photo (``DenoiseConfig(rounds=1)`` applied again and again), so a
later round starts from a cleaner NeRF. The objects, their cached
single-view TTO and the evaluation views are ``benchmarks.bench_denoiser_selection``'s; scores
after each round at every third view after the input. ``--part K --parts N`` runs every N-th
pair of objects (one process a core) and ``--merge`` writes
``benchmarks/results/denoise_rounds.json`` (``denoise_rounds_<candidate>.json`` for another
denoiser) from the parts.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from benchmarks.bench_denoise import RUN
from benchmarks.bench_denoiser_selection import (
    CANDIDATES,
    DEVELOPMENT,
    SHIPPED,
    TTO_CACHE,
    development_object,
    development_objects,
    ensure_candidate,
    scored,
)
from benchmarks.common import ROOT, write_result

PARTS = ROOT / "runs" / "denoise" / "rounds"


def parts_folder(denoiser: str):
    return PARTS if denoiser == SHIPPED else PARTS.parent / f"rounds-{denoiser}"


def run_part(objects: list[str], rounds: int, part: int, denoiser_name: str = SHIPPED) -> None:
    from tqdm import tqdm

    from model.denoise.finetune import DenoiseConfig, denoise_and_finetune, ring_poses
    from model.denoise.io import load_denoiser
    from model.nerf import config
    from model.nerf.rays import Intrinsics
    from model.prior.io import load_prior

    denoiser, _ = load_denoiser(ensure_candidate(denoiser_name))
    prior = load_prior(RUN)
    field, camera = prior.net.cfg.field, config.from_dict(Intrinsics, prior.meta["camera"])
    rows = {}
    for object_id in tqdm(objects, desc=f"part {part}", unit="object"):
        cached = TTO_CACHE / f"{object_id}.safetensors"
        if not cached.is_file():
            raise SystemExit(f"{cached} is missing: run `python -m benchmarks.bench_denoiser_selection` first (it inverts the objects)")
        inputs, evaluation, params, grid = development_object(prior, object_id)
        row = {"tto": scored(prior, params, grid, evaluation)}
        for count in range(1, rounds + 1):
            began = time.perf_counter()
            result = denoise_and_finetune(params, field, prior.scene, denoiser, ring_poses(), camera, DenoiseConfig(rounds=1), grid=grid,
                                          inputs=(inputs.images, inputs.c2w, inputs.cameras))
            params, grid = result.params, result.grid
            row[f"rounds {count}"] = {**scored(prior, params, grid, evaluation), "round_s": time.perf_counter() - began}
            print(f"  {object_id} after {count} round(s): {row[f'rounds {count}']['psnr']:.2f} / {row[f'rounds {count}']['psnr_fg']:.2f} dB", flush=True)
        rows[object_id] = row
    folder = parts_folder(denoiser_name)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"part{part}.json").write_text(json.dumps(rows, indent=2))


def merge(objects: list[str], parts: int, rounds: int, command: str, denoiser_name: str = SHIPPED) -> int:
    rows = {}
    for part in range(parts):
        path = parts_folder(denoiser_name) / f"part{part}.json"
        if not path.is_file():
            print(f"{path} is missing: run --part {part} --parts {parts} first", file=sys.stderr)
            return 1
        rows.update(json.loads(path.read_text()))
    if set(rows) != set(objects):
        print(f"the parts hold {sorted(rows)}, not the development objects {objects}", file=sys.stderr)
        return 1
    stages = list(next(iter(rows.values())))
    mean = {stage: {k: sum(r[stage][k] for r in rows.values()) / len(rows) for k in ("psnr", "psnr_fg", "psnr_fg_gt_mask")} for stage in stages}
    for stage in stages[1:]:
        print(f"{stage}: {mean[stage]['psnr'] - mean['tto']['psnr']:+.2f} dB full, {mean[stage]['psnr_fg'] - mean['tto']['psnr_fg']:+.2f} dB foreground over TTO")
    write_result("denoise_rounds" if denoiser_name == SHIPPED else f"denoise_rounds_{denoiser_name}", {
        "command": command, "data": str(DEVELOPMENT.relative_to(ROOT)), "objects": objects, "denoiser": denoiser_name,
        "denoiser_pairs": CANDIDATES[denoiser_name][0], "rounds": rounds,
        "evaluated_at": "every third view after the input (views 1, 4, 7, ...)",
        "round_s_note": "seconds of one round (render, denoise, finetune) with the other part's process on the second core",
        "mean": mean, "rows": rows,
    })
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=4, help="deformed copies (bench_denoiser_selection's)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--part", type=int, default=0)
    parser.add_argument("--parts", type=int, default=1)
    parser.add_argument("--merge", action="store_true", help="write the result from the parts")
    parser.add_argument("--denoiser", default=SHIPPED, choices=list(CANDIDATES), help="the candidate denoiser (trained when missing)")
    args = parser.parse_args(argv)
    from model.prior.io import load_prior

    objects = development_objects(load_prior(RUN), args.objects)
    command = f"python -m benchmarks.bench_denoise_rounds --rounds {args.rounds}" + ("" if args.denoiser == SHIPPED else f" --denoiser {args.denoiser}")
    if args.merge:
        return merge(objects, args.parts, args.rounds, f"{command} --part K --parts {args.parts} (K = 0..{args.parts - 1}, "
                     "one process a core), then --merge", args.denoiser)
    run_part(objects[args.part :: args.parts], args.rounds, args.part, args.denoiser)
    if args.parts == 1:
        return merge(objects, 1, args.rounds, command, args.denoiser)
    return 0


if __name__ == "__main__":
    sys.exit(main())
