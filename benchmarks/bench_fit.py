"""Per-object fit quality and time on real Sweet Home 3D chairs at 128x128, with masks and without.

Each object is fitted by ``hypnerf fit`` in its own process, once with the visual hull carved from
the masks as the occupancy grid's start (``masks``) and once with the grid grown from the field's
density alone (``no-masks``, ``--no-masks``); the figures are that command's ``metrics.json``:
held-out full-image and foreground PSNR beside the blank-image floor, SSIM, Chamfer distance of the
marching-cubes mesh to the ground-truth mesh (scene-box units), fit wall time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import torch

from benchmarks.common import ROOT, ensure_sh3d_chairs, hypnerf, write_result
from model.data.dataset import load_index
from model.eval.field import evaluation_code_version

RUNS = ROOT / "runs" / "bench-fit"
MODES = {"masks": [], "no-masks": ["--no-masks"]}
KEYS = ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg", "ssim", "chamfer", "wall_s", "render_ms", "samples_per_ray", "occupied_fraction")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--objects", type=int, default=6)
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args(argv)
    data = ensure_sh3d_chairs(args.objects)
    rows = []
    for entry in list(load_index(data))[: args.objects]:
        for mode, flags in MODES.items():
            out = RUNS / mode / entry.id
            done = out / "metrics.json"
            m = json.loads(done.read_text()) if done.is_file() else {}
            # a fit made by this code with these steps is kept (an interrupted benchmark resumes)
            if m.get("code_version") != evaluation_code_version() or m.get("steps") != args.steps:
                hypnerf("fit", "--data", str(data), "--object", entry.id, "--out", str(out), "--steps", str(args.steps), *flags)
                m = json.loads(done.read_text())
            rows.append({"object": entry.id, "mode": mode, **{k: m[k] for k in KEYS}})
            print(f"{entry.id} [{mode}]: {m['psnr']:.2f} dB (fg {m['psnr_fg']:.2f}, floor {m['floor_psnr']:.2f} / {m['floor_psnr_fg']:.2f}), {m['wall_s']:.0f} s")
    mean = {mode: {k: statistics.fmean(r[k] for r in rows if r["mode"] == mode) for k in KEYS} for mode in MODES}
    write_result(
        "fit",
        {
            "command": "python -m benchmarks.bench_fit " + " ".join(sys.argv[1:] if argv is None else argv),
            "dataset": "sweethome3d-furniture chairs, 91 training views, 128x128",
            "steps": args.steps,
            "threads": torch.get_num_threads(),
            "foreground": "pixels where the ground-truth alpha > 0 or the rendered opacity >= 1/255; floors are a blank white image on the same pixels",
            "objects": rows,
            "mean": mean,
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
