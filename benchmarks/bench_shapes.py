"""Does the prior generalise better with more training shapes, and with a variational codebook?

Four priors trained with the same budget (``--steps``, 8 objects and 4096 rays a step), each
evaluated on the same test split (11 unseen chairs, one input view, 91 evaluation views):

- ``26``: the first 104 train-split instances (26 meshes with their colour variants);
- ``51``: every train-split mesh (the main prior's data, at this budget);
- ``153``: every train-split mesh plus two deformed copies of each (``hypnerf data import-sh3d
  --augment 2``: anisotropic scaling, a height stretch about a cut, mirroring; never of a
  test-split mesh; the test split is checked to be the same objects);
- ``51-noise``: the 51 meshes with code noise (``--code-noise``), a variational codebook with a
  fixed posterior width, compared with ``51`` on generalisation, on its own training views, and
  on unconditional samples and interpolation paths (``hypnerf eval sampling``).

Every stage runs the ``hypnerf`` command a user would, in ``runs/shapes/``, and is skipped when its
output is there, so the script resumes. Writes ``benchmarks/results/shapes.json`` and
``benchmarks/results/variational.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.common import ROOT, hypnerf, write_result

DATA = ROOT / "data" / "sh3d-chair-variants"
AUGMENTED = ROOT / "data" / "sh3d-chair-augmented"
RUNS = ROOT / "runs" / "shapes"
ROWS = "tto,nearest,mean_code"
PRIORS = {
    "26": {"data": DATA, "train": ["--limit", "104"]},
    "51": {"data": DATA, "train": []},
    "153": {"data": AUGMENTED, "train": []},
    "51-noise": {"data": DATA, "train": ["--code-noise", "0.5"]},
}


def _run_dir(name: str) -> Path:
    return RUNS / f"s{name}"


def _test_split(data: Path) -> list[str]:
    index = json.loads((data / "index.json").read_text())
    return sorted(o["id"] for o in index["objects"] if o["split"] == "test")


def prepare() -> None:
    if not (DATA / "index.json").is_file():
        raise SystemExit(f"{DATA} is missing; run `make bundle` (or its dataset step) first")
    if not (AUGMENTED / "index.json").is_file():
        hypnerf("data", "import-sh3d", "--out", str(AUGMENTED), "--category", "chair", "--variants", "4", "--augment", "2",
                "--views", "91", "--res", "128")
    if _test_split(AUGMENTED) != _test_split(DATA):
        raise SystemExit(f"the test split of {AUGMENTED} differs from {DATA}'s: augmentation must not move objects between splits")


def train_and_evaluate(steps: int) -> None:
    for name, spec in PRIORS.items():
        run = _run_dir(name)
        if not (run / "prior.json").is_file():
            resume = ["--resume"] if (run / "checkpoint.pt").is_file() else []
            hypnerf("train", "--data", str(spec["data"]), "--out", str(run), "--preset", "cpu", "--steps", str(steps), "--objects-per-step", "8",
                    "--rays", "4096", "--validate-every", "1000", "--checkpoint-every", "500", *spec["train"], *resume)
        report = RUNS / f"s{name}-gen.json"
        if not report.is_file():
            hypnerf("eval", "generalization", "--run", str(run), "--data", str(spec["data"]), "--json", str(report), "--rows", ROWS)
    for name in ("51", "51-noise"):
        report = RUNS / f"s{name}-sampling.json"
        if not report.is_file():
            hypnerf("eval", "sampling", "--run", str(_run_dir(name)), "--samples", "12", "--json", str(report))


def _summary(name: str) -> dict:
    meta = json.loads((_run_dir(name) / "prior.json").read_text())
    summary = meta["summary"]
    final = summary["final"]
    gen = json.loads((RUNS / f"s{name}-gen.json").read_text())
    return {
        "shapes": summary["shapes"], "instances": summary["instances"], "steps": summary["steps"], "train_wall_s": summary["wall_s"],
        "code_noise": meta["train"].get("code_noise", 0.0),
        "training_views": {k: final[f"val_{k}"] for k in ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg")},
        "test": {row: {k: gen["rows"][row][k] for k in ("psnr", "psnr_fg", "ssim", "fid")} for row in gen["rows"]},
        "tto_s": gen["tto_s"],
        "test_objects": gen["objects"],
        "floor_psnr": gen["floor_psnr"], "floor_psnr_fg": gen["floor_psnr_fg"],
    }


def _midpoint_excess(paths: list[dict]) -> float:
    """Mean over shape paths of the haze at the midpoint minus the mean haze at the two ends."""
    excess = []
    for path in paths:
        haze = path["shape_path_haze"]
        excess.append(haze[len(haze) // 2] - 0.5 * (haze[0] + haze[-1]))
    return sum(excess) / len(excess)


def write_reports(steps: int) -> None:
    rows = {name: _summary(name) for name in ("26", "51", "153")}
    write_result("shapes", {
        "rows": rows, "steps": steps, "rows_computed": ROWS,
        "augmentation": "two deformed copies of each train-split mesh (model.data.augment), each in 4 colour variants",
        "command": "python -m benchmarks.bench_shapes",
    })
    variational = {}
    for name in ("51", "51-noise"):
        sampling = json.loads((RUNS / f"s{name}-sampling.json").read_text())
        variational[name] = {
            **_summary(name),
            "samples_validity": sampling["samples_validity"],
            "training_codes_validity": sampling["training_codes_validity"],
            "distance_to_nearest_training_code": sampling["distance_to_nearest_training_code"],
            "shape_midpoint_haze_excess": _midpoint_excess(sampling["interpolation"]),
            "interpolation": sampling["interpolation"],
        }
    write_result("variational", {
        "rows": variational, "steps": steps, "haze_metric": "share of visible pixels (opacity > 0.05) whose opacity is below 0.95",
        "midpoint_metric": "haze at the middle of a shape interpolation path minus the mean haze at its two ends (0: as sharp as the ends)",
        "command": "python -m benchmarks.bench_shapes",
    })


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=4000, help="training steps of every prior (default 4000)")
    args = parser.parse_args(argv)
    RUNS.mkdir(parents=True, exist_ok=True)
    prepare()
    train_and_evaluate(args.steps)
    write_reports(args.steps)
    return 0


if __name__ == "__main__":
    sys.exit(main())
