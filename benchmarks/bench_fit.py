"""Per-object fit quality and time on real Sweet Home 3D chairs at 128x128.

Each object is fitted by ``hypnerf fit`` in its own process; the figures are that command's
``metrics.json`` (held-out PSNR/SSIM over the fixed evaluation views, Chamfer distance of the
marching-cubes mesh to the ground-truth mesh, fit wall time).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import torch

from benchmarks.common import ROOT, ensure_sh3d_chairs, hypnerf, write_result
from model.data.dataset import load_index

RUNS = ROOT / "runs" / "bench-fit"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--objects", type=int, default=6)
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args(argv)
    data = ensure_sh3d_chairs(args.objects)
    rows = []
    for entry in list(load_index(data))[: args.objects]:
        out = RUNS / entry.id
        hypnerf("fit", "--data", str(data), "--object", entry.id, "--out", str(out), "--steps", str(args.steps))
        m = json.loads((out / "metrics.json").read_text())
        rows.append({"object": entry.id, "name": entry.extra.get("name"), **{k: m[k] for k in ("psnr", "ssim", "chamfer", "wall_s", "render_ms")}})
        print(f"{entry.id}: {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, Chamfer {m['chamfer']:.4f}, {m['wall_s']:.0f} s")
    mean = {k: statistics.fmean(r[k] for r in rows) for k in ("psnr", "ssim", "chamfer", "wall_s")}
    write_result(
        "fit",
        {
            "command": "python -m benchmarks.bench_fit " + " ".join(sys.argv[1:] if argv is None else argv),
            "dataset": "sweethome3d-furniture chairs, 91 training views, 128x128",
            "steps": args.steps,
            "threads": torch.get_num_threads(),
            "objects": rows,
            "mean": mean,
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
