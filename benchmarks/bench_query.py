"""The query network on the Sweet Home 3D chair prior: training, retrieval from new views (clean
and cluttered), text-to-NeRF on held-out prompts with the time each stage of a query takes, and
unconditional sampling with interpolation paths, and TTO of unseen objects started from the
query network's guess against the mean code.

Each stage runs the ``hypnerf`` command a user would and skips itself when its output is already
there (delete a file under ``benchmarks/results/`` or the query run to redo a stage). Embeddings of
the training renders are cached (``~/.cache/hypnerf/embeddings``), so retraining costs seconds.
"""

from __future__ import annotations

import argparse
import sys

from benchmarks.common import RESULTS, ROOT, hypnerf

DATA = ROOT / "data" / "sh3d-chair-variants"
PRIOR = ROOT / "runs" / "prior-cpu"
QUERY = ROOT / "runs" / "query" / "cpu"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--views", type=int, default=48, help="training renders embedded per instance")
    parser.add_argument("--head", default="shape-codebook", help="the query network's head (see hypnerf train-query --help)")
    parser.add_argument("--query-views", type=int, default=2, help="new random views per instance for retrieval")
    parser.add_argument("--prompts", type=int, default=80, help="held-out prompts asked for (fewer when fewer (colour, type) pairs exist)")
    parser.add_argument("--samples", type=int, default=12)
    parser.add_argument("--tto-objects", type=int, default=11, help="unseen test objects for TTO started from the query (0 skips it)")
    args = parser.parse_args(argv)
    if not (PRIOR / "hypernet.safetensors").is_file():
        print(f"{PRIOR} holds no trained prior; run `python -m benchmarks.bench_prior` first", file=sys.stderr)
        return 1
    RESULTS.mkdir(parents=True, exist_ok=True)
    if not (QUERY / "query.safetensors").is_file():
        hypnerf("train-query", "--run", str(PRIOR), "--data", str(DATA), "--out", str(QUERY), "--views", str(args.views), "--head", args.head)
    if not (RESULTS / "retrieval.json").is_file():
        hypnerf("eval", "retrieval", "--run", str(PRIOR), "--data", str(DATA), "--query", str(QUERY), "--views", str(args.query_views),
                "--json", str(RESULTS / "retrieval.json"), "--grid", str(RESULTS / "retrieval_clutter.png"))
    if not (RESULTS / "text_to_nerf.json").is_file():
        hypnerf("eval", "text-to-nerf", "--run", str(PRIOR), "--data", str(DATA), "--query", str(QUERY), "--prompts", str(args.prompts),
                "--json", str(RESULTS / "text_to_nerf.json"), "--grid", str(RESULTS / "text_to_nerf.png"))
    for seed in (1, 2):  # further draws of held-out prompts, a check on choices made on the first
        if not (RESULTS / f"text_to_nerf_seed{seed}.json").is_file():
            hypnerf("eval", "text-to-nerf", "--run", str(PRIOR), "--data", str(DATA), "--query", str(QUERY), "--prompts", str(args.prompts),
                    "--seed", str(seed), "--json", str(RESULTS / f"text_to_nerf_seed{seed}.json"),
                    "--grid", str(ROOT / "runs" / "query" / f"text_to_nerf_seed{seed}.png"))
    if not (RESULTS / "text_to_nerf_no_colour_words.json").is_file():  # the same prompts embedded as they are
        hypnerf("eval", "text-to-nerf", "--run", str(PRIOR), "--data", str(DATA), "--query", str(QUERY), "--prompts", str(args.prompts),
                "--no-colour-words", "--json", str(RESULTS / "text_to_nerf_no_colour_words.json"),
                "--grid", str(ROOT / "runs" / "query" / "text_to_nerf_no_colour_words.png"))
    if not (RESULTS / "sampling.json").is_file():
        hypnerf("eval", "sampling", "--run", str(PRIOR), "--samples", str(args.samples), "--json", str(RESULTS / "sampling.json"),
                "--grid", str(RESULTS / "sampling.png"), "--interpolation-grid", str(RESULTS / "interpolation.png"))
    if args.tto_objects and not (RESULTS / "query_tto.json").is_file():
        hypnerf("eval", "query-tto", "--run", str(PRIOR), "--data", str(DATA), "--query", str(QUERY), "--objects", str(args.tto_objects),
                "--json", str(RESULTS / "query_tto.json"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
