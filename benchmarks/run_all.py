"""``make bench``: every benchmark in turn, then BENCHMARKS.md from their results."""

from __future__ import annotations

import sys

from benchmarks import bench_encoding, bench_fit, bench_import, bench_render, report


def main() -> int:
    steps = (lambda: bench_encoding.main([]), lambda: bench_fit.main([]), bench_render.main, bench_import.main)
    for step in steps:
        code = step()
        if code:
            return code
    return report.main()


if __name__ == "__main__":
    sys.exit(main())
