"""Renderer speed against error: ``hypnerf bench render`` on the first fitted benchmark chair."""

from __future__ import annotations

import sys

from benchmarks.bench_fit import RUNS
from benchmarks.common import RESULTS, hypnerf


def main() -> int:
    fits = sorted(p for p in (RUNS / "masks").glob("*") if (p / "field.safetensors").is_file())
    if not fits:
        print("no fitted chair under runs/bench-fit/masks: run `python -m benchmarks.bench_fit` first", file=sys.stderr)
        return 2
    RESULTS.mkdir(parents=True, exist_ok=True)
    hypnerf("bench", "render", "--fit", str(fits[0]), "--json", str(RESULTS / "render.json"), "--views", "4", "--repeats", "3")
    return 0


if __name__ == "__main__":
    sys.exit(main())
