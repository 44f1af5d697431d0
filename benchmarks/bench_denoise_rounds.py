"""Rounds of denoise-and-finetune on the development set (deformed copies of training meshes).

Each round renders the ring poses of the NeRF the round before finetuned, denoises them with the
shipped denoiser (or another of ``bench_denoiser_selection``'s candidates, ``--denoiser``) and
finetunes on them and the input photo (``DenoiseConfig(rounds=1)`` applied again and again, at
the default input share or ``--input-share``), so a later round starts from a cleaner NeRF. The
photo's mirror image joins it only with ``--mirror-inputs``: the studies here were run without it,
before it became ``DenoiseConfig``'s default. The objects, their cached single-view TTO and the
evaluation views are ``benchmarks.bench_denoiser_selection``'s; scores after each round at every
third view after the input, each object's row kept under ``runs/denoise/rounds/<variant>/`` (the
denoiser's name, with the share when it is not the default and ``_mirror`` with the mirrored
photo; a rerun or a larger ``--objects`` scores only what is missing). ``--part K --parts N``
runs every N-th object (one process a core) and ``--merge`` writes
``benchmarks/results/denoise_rounds_<variant>_<N>objects.json`` (``denoise_rounds.json`` for the
study that chose the number of rounds, ``STUDY``).
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
    FIRST_OBJECTS,
    SHIPPED,
    development_object,
    development_objects,
    ensure_candidate,
    scored,
)
from benchmarks.common import ROOT, write_result

ROWS = ROOT / "runs" / "denoise" / "rounds"
# the study that chose the number of rounds (the shipped denoiser, the first development objects,
# three rounds) keeps the name denoise_rounds.json
STUDY = ("denoiser-tto", FIRST_OBJECTS, 3)


def variant(denoiser: str, input_share: float | None, mirror_inputs: bool = False) -> str:
    """The denoiser's name, with the input share when it is not the default, and ``_mirror`` when
    the input photo's mirror image joins the finetune views."""
    return denoiser + ("" if input_share is None else f"_share{input_share:g}") + ("_mirror" if mirror_inputs else "")


def result_name(name: str, objects: int, rounds: int) -> str:
    return "denoise_rounds" if (name, objects, rounds) == STUDY else f"denoise_rounds_{name}_{objects}objects"


def row_file(name: str, object_id: str):
    """Where an object's scores after each round with the denoiser variant ``name`` are kept (a rerun skips it)."""
    return ROWS / name / f"{object_id}.json"


def run_part(objects: list[str], rounds: int, part: int, denoiser_name: str, input_share: float | None = None,
             mirror_inputs: bool = False) -> None:
    """Score each object after each of ``rounds`` rounds, unless its row already holds them."""
    from tqdm import tqdm

    from model.denoise.finetune import DenoiseConfig, denoise_and_finetune, ring_poses
    from model.denoise.io import load_denoiser
    from model.nerf import config
    from model.nerf.rays import Intrinsics
    from model.prior.io import load_prior

    denoiser, _ = load_denoiser(ensure_candidate(denoiser_name))
    prior = load_prior(RUN)
    field, camera = prior.net.cfg.field, config.from_dict(Intrinsics, prior.meta["camera"])
    settings = DenoiseConfig(rounds=1, mirror_inputs=mirror_inputs, **({} if input_share is None else {"input_share": input_share}))
    for object_id in tqdm(objects, desc=f"part {part}", unit="object"):
        path = row_file(variant(denoiser_name, input_share, mirror_inputs), object_id)
        if path.is_file() and f"rounds {rounds}" in json.loads(path.read_text()):
            continue
        inputs, evaluation, params, grid = development_object(prior, object_id)  # inverts the object when its TTO is not cached
        row = {"tto": scored(prior, params, grid, evaluation)}
        for count in range(1, rounds + 1):
            began = time.perf_counter()
            result = denoise_and_finetune(params, field, prior.scene, denoiser, ring_poses(), camera, settings, grid=grid,
                                          inputs=(inputs.images, inputs.c2w, inputs.cameras))
            params, grid = result.params, result.grid
            row[f"rounds {count}"] = {**scored(prior, params, grid, evaluation), "round_s": time.perf_counter() - began}
            print(f"  {object_id} after {count} round(s): {row[f'rounds {count}']['psnr']:.2f} / {row[f'rounds {count}']['psnr_fg']:.2f} dB", flush=True)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(row, indent=2))


def merge(objects: list[str], rounds: int, command: str, denoiser_name: str, input_share: float | None = None,
          mirror_inputs: bool = False) -> int:
    from model.denoise.finetune import DenoiseConfig

    rows = {}
    for object_id in objects:
        path = row_file(variant(denoiser_name, input_share, mirror_inputs), object_id)
        row = json.loads(path.read_text()) if path.is_file() else {}
        if f"rounds {rounds}" not in row:
            print(f"{path} does not hold {rounds} round(s): run the parts first", file=sys.stderr)
            return 1
        rows[object_id] = {stage: row[stage] for stage in ("tto", *(f"rounds {k}" for k in range(1, rounds + 1)))}
    stages = list(next(iter(rows.values())))
    mean = {stage: {k: sum(r[stage][k] for r in rows.values()) / len(rows) for k in ("psnr", "psnr_fg", "psnr_fg_gt_mask")} for stage in stages}
    for stage in stages[1:]:
        print(f"{stage}: {mean[stage]['psnr'] - mean['tto']['psnr']:+.2f} dB full, {mean[stage]['psnr_fg'] - mean['tto']['psnr_fg']:+.2f} dB foreground over TTO")
    write_result(result_name(variant(denoiser_name, input_share, mirror_inputs), len(objects), rounds), {
        "command": command, "data": str(DEVELOPMENT.relative_to(ROOT)), "objects": objects, "denoiser": denoiser_name,
        "denoiser_pairs": CANDIDATES[denoiser_name][0], "rounds": rounds,
        "input_share": DenoiseConfig().input_share if input_share is None else input_share, "mirror_inputs": mirror_inputs,
        "evaluated_at": "every third view after the input (views 1, 4, 7, ...)",
        "round_s_note": "seconds of one round (render, denoise, finetune) with another process on the second core",
        "mean": mean, "rows": rows,
    })
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=FIRST_OBJECTS, help="deformed copies (bench_denoiser_selection's)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--part", type=int, default=0)
    parser.add_argument("--parts", type=int, default=1)
    parser.add_argument("--merge", action="store_true", help="write the result from the parts")
    parser.add_argument("--denoiser", default=SHIPPED, choices=list(CANDIDATES), help="the candidate denoiser (trained when missing)")
    parser.add_argument("--input-share", type=float, help="the input photo's share of the finetune views (default: DenoiseConfig's)")
    parser.add_argument("--mirror-inputs", action="store_true", help="the input photo's mirror image joins the finetune views")
    args = parser.parse_args(argv)
    from model.prior.io import load_prior

    objects = development_objects(load_prior(RUN), args.objects)
    command = (f"python -m benchmarks.bench_denoise_rounds --objects {args.objects} --rounds {args.rounds} --denoiser {args.denoiser}"
               + ("" if args.input_share is None else f" --input-share {args.input_share:g}")
               + (" --mirror-inputs" if args.mirror_inputs else ""))
    if args.merge:
        return merge(objects, args.rounds, f"{command} --part K --parts {args.parts} (K = 0..{args.parts - 1}, "
                     "one process a core), then --merge", args.denoiser, args.input_share, args.mirror_inputs)
    run_part(objects[args.part :: args.parts], args.rounds, args.part, args.denoiser, args.input_share, args.mirror_inputs)
    if args.parts == 1:
        return merge(objects, args.rounds, command, args.denoiser, args.input_share, args.mirror_inputs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
