"""Hash-encoding throughput: hypnerf's fused CPU kernel against nerfstudio's torch HashEncoding.

Runs every implementation side by side in one process (interleaved repeat by repeat, so they see
the same machine load), with the same thread count and number of uniformly random points, and reports the median
points per second of each pass:

- ``forward``: encoding under ``torch.no_grad()``;
- ``forward+backward``: encoding, then backward of a fixed upstream gradient to both the table
  parameters and the points (nerfstudio's torch path is differentiable in both too).

Implementations: ``hypnerf-kernel`` (``model.nerf.encodings.hashgrid.encode`` on CPU: the C++/OpenMP extension),
``nerfstudio-torch`` (``nerfstudio.field_components.encodings.HashEncoding`` with
``implementation="torch"``; it owns its table as an ``nn.Parameter`` and uses
floor(N_min * b^l) resolutions, hashing every level) and ``hypnerf-reference`` (the pure-PyTorch
path of ``model.nerf.encodings.hashgrid``). ``hypnerf-kernel-batched`` encodes B = 8 objects, each with its
own tables (which only hypnerf supports); every run records its ``batch`` and ``points``.

nerfstudio is a benchmark-only dependency (``pip install --no-deps nerfstudio==1.1.5 ...``); if it
cannot be imported the benchmark says so and exits with status 2 rather than report partial
numbers. Writes ``benchmarks/results/encoding.json``.

    python benchmarks/bench_encoding.py [--points 262144] [--repeats 5] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from model.nerf.encodings.hashgrid import HashGridConfig, encode, encode_reference, init_tables, uses_kernel  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "encoding.json"
PASSES = ("forward", "forward+backward")


def _import_nerfstudio():
    """nerfstudio's HashEncoding class, or None after explaining how to install it."""
    try:
        from nerfstudio.field_components.encodings import HashEncoding
    except Exception as exc:  # any import failure: missing package or one of its imports
        print(
            f"error: nerfstudio's HashEncoding cannot be imported ({type(exc).__name__}: {exc}).\n"
            "Install it for the benchmark with:\n"
            "  .venv/bin/pip install --no-deps nerfstudio==1.1.5 jaxtyping wadler_lindig rich viser msgspec "
            "websockets zstandard",
            file=sys.stderr,
        )
        return None
    return HashEncoding


class Case:
    """One implementation on one problem: callables for each pass, sharing inputs across repeats."""

    def __init__(self, name, batch, n, forward, forward_backward):
        self.name, self.batch, self.n = name, batch, n
        self.passes = {"forward": forward, "forward+backward": forward_backward}
        self.seconds = {p: [] for p in PASSES}

    def run(self, pass_name: str) -> None:
        start = time.perf_counter()
        self.passes[pass_name]()
        self.seconds[pass_name].append(time.perf_counter() - start)

    def points_per_s(self, pass_name: str) -> float:
        return self.batch * self.n / statistics.median(self.seconds[pass_name])


def hypnerf_case(name, fn, cfg, batch, n, generator) -> Case:
    points = torch.rand(batch, n, 3, generator=generator)
    tables = init_tables(cfg, batch, generator=generator)
    upstream = torch.randn(batch, n, cfg.output_dim, generator=generator)
    points_g = points.clone().requires_grad_()
    tables_g = tables.clone().requires_grad_()

    def forward():
        with torch.no_grad():
            fn(points, tables, cfg)

    def forward_backward():
        points_g.grad = tables_g.grad = None
        fn(points_g, tables_g, cfg).backward(upstream)

    return Case(name, batch, n, forward, forward_backward)


def nerfstudio_case(hash_encoding_cls, cfg, n, generator) -> Case:
    enc = hash_encoding_cls(
        num_levels=cfg.levels,
        min_res=cfg.base_resolution,
        max_res=cfg.finest_resolution,
        log2_hashmap_size=cfg.log2_table_size,
        features_per_level=cfg.features,
        implementation="torch",
    )
    points = torch.rand(n, 3, generator=generator)
    upstream = torch.randn(n, cfg.output_dim, generator=generator)
    points_g = points.clone().requires_grad_()

    def forward():
        with torch.no_grad():
            enc(points)

    def forward_backward():
        points_g.grad = None
        enc.zero_grad(set_to_none=True)
        enc(points_g).backward(upstream)

    return Case("nerfstudio-torch", 1, n, forward, forward_backward)


def measure(cases: list[Case], repeats: int) -> None:
    """Warm up once, then interleave the cases pass by pass, repeat by repeat."""
    for case in cases:
        for p in PASSES:
            case.passes[p]()
    for _ in range(repeats):
        for p in PASSES:
            for case in cases:
                case.run(p)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the process exit status (2: nerfstudio missing, 1: no kernel)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=2**18, help="points for the B=1 comparison")
    parser.add_argument("--batch", type=int, default=8, help="objects in the batched kernel run")
    parser.add_argument("--batch-points", type=int, default=2**15, help="points per object in the batched run")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    hash_encoding_cls = _import_nerfstudio()
    if hash_encoding_cls is None:
        return 2
    torch.set_num_threads(args.threads)
    cfg = HashGridConfig(levels=16, log2_table_size=11, features=2, base_resolution=16, finest_resolution=2048)
    if not uses_kernel(torch.empty(1, 1, 3), cfg):
        print("error: the hypnerf C++ kernel is not in use (HYPNERF_PURE_TORCH set or build failed)", file=sys.stderr)
        return 1

    g = torch.Generator().manual_seed(0)
    ours = hypnerf_case("hypnerf-kernel", encode, cfg, 1, args.points, g)
    theirs = nerfstudio_case(hash_encoding_cls, cfg, args.points, g)
    reference = hypnerf_case("hypnerf-reference", encode_reference, cfg, 1, args.points, g)
    batched = hypnerf_case("hypnerf-kernel-batched", encode, cfg, args.batch, args.batch_points, g)
    cases = [ours, theirs, reference, batched]
    measure(cases, args.repeats)

    runs = [
        {"impl": c.name, "pass": p, "batch": c.batch, "points": c.n, "points_per_s": c.points_per_s(p)}
        for c in cases
        for p in PASSES
    ]
    speedup = {p: ours.points_per_s(p) / theirs.points_per_s(p) for p in PASSES}
    result = {
        "config": cfg.to_dict(),
        "points": args.points,
        "threads": args.threads,
        "repeats": args.repeats,
        "runs": runs,
        "speedup_vs_nerfstudio": speedup,
        "command": shlex.join(sys.orig_argv),
        "torch": torch.__version__,
        "environment": {k: v for k, v in os.environ.items() if k.startswith(("MALLOC_", "OMP_", "THP_", "HYPNERF_"))},
    }

    print(f"hash encoding, L={cfg.levels} T=2^{cfg.log2_table_size} F={cfg.features}, {args.threads} threads, "
          f"median of {args.repeats}")
    print(f"{'impl':<24} {'B x N':>12} {'pass':<17} {'M points/s':>11} {'vs nerfstudio':>14}")
    for r in runs:
        ratio = r["points_per_s"] / theirs.points_per_s(r["pass"])
        print(f"{r['impl']:<24} {r['batch']:>3} x {r['points']:<8} {r['pass']:<17} {r['points_per_s'] / 1e6:>11.3f} "
              f"{ratio:>13.1f}x")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
