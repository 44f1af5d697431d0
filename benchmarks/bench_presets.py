"""Why the ``cpu`` preset and the hull: size, speed and quality of training choices on the same chairs.

Three hypernetworks emit the same hash-grid NeRF:
- ``paper``: the official code's sizes (codes 512 + 512, heads of 3 x 512, full-rank table head);
- ``cpu-full-rank``: the ``cpu`` preset without the low-rank bottleneck in front of the table head;
- ``cpu``: codes 128 + 128, heads of 2 x 256, rank-128 table head (what ``hypnerf train`` uses).

Quality: each is trained for the same steps on the same instances (the first ``--instances`` of
the train split: a few meshes with their colour variants) and scored on one held-out view of every
instance, each NeRF with the occupancy grid of its own density. Speed: a short run on a quiet
machine, rays/s after warm-up. Size: parameters and bytes of the exported (fp16) prior.

The same measurements compare where training rays take samples (``TrainConfig.occupancy``): the
visual hull carved from the masks (what ``hypnerf train`` uses), a band around the ground-truth
mesh surface, and the whole box without empty-space skipping.

Quality runs are kept under ``runs/presets/`` and skipped when present, so the timing stage can
be repeated alone (``--timing-only``) when the quality runs shared the machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

from benchmarks.bench_prior import DATA, RUNS, ensure_dataset
from benchmarks.common import RESULTS, write_result
from model.data.category import load_category
from model.prior.hypernet import HyperNetConfig, preset
from model.prior.io import PRIOR_WEIGHTS, load_prior
from model.train.prior import TrainConfig, train, validate, validation_views

PRESETS: dict[str, HyperNetConfig] = {
    "paper": preset("paper"),
    "cpu-full-rank": replace(preset("cpu"), table_rank=None),
    "cpu": preset("cpu"),
}


# the hull is the "cpu" preset's own run
OCCUPANCY = {"hull": "cpu", "mesh": "occupancy-mesh", "box": "occupancy-box"}


def train_config(steps: int, validate_every: int, occupancy: str = "hull") -> TrainConfig:
    return TrainConfig(
        steps=steps, objects_per_step=8, rays_per_step=4096, validate_every=validate_every, checkpoint_every=max(steps, 1), log_every=10, occupancy=occupancy
    )


def quality(name: str, cfg: HyperNetConfig, steps: int, instances: int, occupancy: str = "hull") -> dict:
    run = RUNS / "presets" / name
    if not (run / PRIOR_WEIGHTS).is_file():
        train(DATA, run, cfg, train_config(steps, validate_every=0, occupancy=occupancy), limit=instances)
    prior = load_prior(run)
    net, meta = prior.net, prior.meta
    data = load_category(DATA, "train", instances, progress=False)
    views = validation_views(data, instances)
    counts = net.head_parameter_counts()
    scores = validate(net, data, views, torch.device("cpu"))
    return {
        "steps": meta["summary"]["steps"],
        "wall_s": meta["summary"]["wall_s"],
        "held_out_psnr": scores["psnr"],
        "held_out_psnr_fg": scores["psnr_fg"],
        "floor_psnr": scores["floor_psnr"],
        "floor_psnr_fg": scores["floor_psnr_fg"],
        "weights_bytes": (run / PRIOR_WEIGHTS).stat().st_size,
        "parameters": sum(counts.values()),
        "table_head_parameters": counts["tables"],
    }


def timing(cfg: HyperNetConfig, steps: int, instances: int, occupancy: str = "hull") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        train(DATA, Path(tmp), cfg, train_config(steps, validate_every=0, occupancy=occupancy), limit=instances, progress=False)
        history = json.loads((Path(tmp) / "history.json").read_text())
    warm = [h for h in history if h["step"] >= 10] or history
    rays = statistics.median(h["rays_per_s"] for h in warm)
    return {"rays_per_s": rays, "steps_per_s": rays / 4096, "samples_per_ray": statistics.median(h["samples_per_ray"] for h in warm)}


TIMED = ("rays_per_s", "steps_per_s", "samples_per_ray")


def measured_row(row: dict, key: str, previous: list[dict] | None, measure_quality, measure_speed) -> dict:
    """``row`` with its quality figures (measured, or the ones on file when ``previous`` is given)
    and freshly measured speed."""
    if previous is not None:
        row.update({k: v for k, v in next(r for r in previous if r[key] == row[key]).items() if k not in TIMED})
    else:
        print(f"quality run: {key} {row[key]}", file=sys.stderr)
        row.update(measure_quality())
    print(f"timing run: {key} {row[key]}", file=sys.stderr)
    row.update(measure_speed())
    print(json.dumps(row), file=sys.stderr)
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000, help="training steps of each quality run")
    parser.add_argument("--instances", type=int, default=16, help="first N instances of the train split")
    parser.add_argument("--timing-steps", type=int, default=60)
    parser.add_argument("--timing-only", action="store_true", help="re-measure speed only, keeping the quality figures on file (and their --steps and --instances)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (timings are comparable only at equal threads on a quiet machine)")
    args = parser.parse_args(argv)
    ensure_dataset(4)
    torch.set_num_threads(args.threads)
    previous = json.loads((RESULTS / "presets.json").read_text()) if (RESULTS / "presets.json").is_file() else {}
    if args.timing_only and not previous:
        parser.error(f"--timing-only re-measures speed beside quality figures on file, and {RESULTS / 'presets.json'} does not exist; run without it first")
    if args.timing_only:
        # the speed is measured on the instances the quality figures on file were trained on
        args.steps, args.instances = previous["steps"], previous["instances"]
    rows = [
        measured_row(
            {"preset": name, "shape_code_dim": cfg.shape_code_dim, "color_code_dim": cfg.color_code_dim,
             "head_hidden": cfg.head_hidden, "head_layers": cfg.head_layers, "table_rank": cfg.table_rank},
            "preset", previous["runs"] if args.timing_only else None,
            lambda: quality(name, cfg, args.steps, args.instances),
            lambda: timing(cfg, args.timing_steps, args.instances),
        )
        for name, cfg in PRESETS.items()
    ]
    cpu = PRESETS["cpu"]
    occupancy_rows = [
        measured_row(
            {"occupancy": source}, "occupancy", previous["occupancy"] if args.timing_only else None,
            lambda: {k: v for k, v in quality(name, cpu, args.steps, args.instances, source).items() if k in ("wall_s", "held_out_psnr")},
            lambda: timing(cpu, args.timing_steps, args.instances, source),
        )
        for source, name in OCCUPANCY.items()
    ]
    write_result("presets", {
        "command": "python -m benchmarks.bench_presets",
        "dataset": str(DATA.relative_to(DATA.parents[1])),
        "instances": args.instances,
        "steps": args.steps,
        "objects_per_step": 8,
        "rays_per_step": 4096,
        "threads": torch.get_num_threads(),
        "runs": rows,
        "occupancy": occupancy_rows,
    })
    return 0


if __name__ == "__main__":
    sys.exit(main())
