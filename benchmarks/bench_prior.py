"""The category prior on Sweet Home 3D chairs: training, compression, the ablation without MRHE,
disentanglement, training throughput and its PSNR-against-time curve.

Each stage runs the same ``hypnerf`` command a user would and skips itself when its output is
already there (delete a file under ``benchmarks/results/`` or a run folder to redo a stage).
Training resumes from its checkpoint, so the long stages can be done in parts. The training
curve is drawn with **matplotlib** (Agg backend: no display needed).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.common import RESULTS, ROOT, hypnerf, write_result

DATA = ROOT / "data" / "sh3d-chair-variants"
RUNS = ROOT / "runs"
# the per-object reference fits take as many steps as the fit benchmark (benchmarks/bench_fit.py)
FIT_STEPS = 2000
# 8 objects x 512 rays per step; validation and checkpoints every 1000 steps (each costs a few seconds)
TRAIN_ARGS = ("--objects-per-step", "8", "--rays", "4096", "--validate-every", "1000", "--checkpoint-every", "1000")


def ensure_dataset(variants: int) -> Path:
    if not (DATA / "index.json").is_file():
        hypnerf("data", "import-sh3d", "--out", str(DATA), "--category", "chair", "--variants", str(variants), "--views", "91", "--res", "128")
    return DATA


def ensure_trained(run: Path, preset: str, steps: int, until: int | None) -> bool:
    """Train (or continue) a prior; returns whether it is finished."""
    if (run / "hypernet.safetensors").is_file():
        return True
    args = ["train", "--data", str(DATA), "--out", str(run), "--preset", preset, "--steps", str(steps), *TRAIN_ARGS]
    if (run / "checkpoint.pt").is_file():
        args.append("--resume")
    if until:
        args += ["--until", str(until)]
    hypnerf(*args)
    return (run / "hypernet.safetensors").is_file()


def training_report(run: Path, name: str) -> dict:
    history = json.loads((run / "history.json").read_text())
    meta = json.loads((run / "prior.json").read_text())
    summary = meta["summary"]
    window = history[-10:]
    report = {
        "command": f"hypnerf train --data {DATA.relative_to(ROOT)} --out {run.relative_to(ROOT)} --preset {name} --steps {summary['steps']} {' '.join(TRAIN_ARGS)}",
        "preset": name,
        "instances": summary["instances"],
        "shapes": summary["shapes"],
        "steps": summary["steps"],
        "wall_s": summary["wall_s"],
        "workers": summary["workers"],
        "threads_per_worker": summary["threads_per_worker"],
        "rays_per_s": sum(h["rays_per_s"] for h in window) / len(window),
        "samples_per_s": sum(h["samples_per_s"] for h in window) / len(window),
        "samples_per_ray": sum(h["samples_per_ray"] for h in window) / len(window),
        "parameters": summary["parameters"],
        "weights_bytes": (run / "hypernet.safetensors").stat().st_size,
        "curve": [{k: h[k] for k in ("step", "elapsed_s", "train_psnr", "val_psnr", "val_psnr_fg", "val_floor_psnr", "val_floor_psnr_fg") if k in h} for h in history if "val_psnr" in h],
    }
    return report


def plot_curves(reports: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for report in reports:
        curve = report["curve"]
        ax.plot([c["elapsed_s"] / 60 for c in curve], [c["val_psnr"] for c in curve], marker="o", markersize=3, label=f"{report['preset']}, {report['steps']} steps")
    ax.set_xlabel("training time on 2 CPU cores (min)")
    ax.set_ylabel("held-out-view PSNR of training instances (dB)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--variants", type=int, default=4, help="colour variants per mesh")
    parser.add_argument("--steps", type=int, default=40000, help="training steps of the cpu prior")
    parser.add_argument("--ablation-steps", type=int, default=3000, help="training steps of the no-MRHE prior and of the hash-grid prior it is compared with")
    parser.add_argument("--until", type=int, help="stop training at this step (resume by running again)")
    parser.add_argument("--objects", type=int, default=10)
    parser.add_argument("--pairs", type=int, default=10)
    parser.add_argument("--skip-ablation", action="store_true")
    args = parser.parse_args(argv)
    ensure_dataset(args.variants)
    RESULTS.mkdir(parents=True, exist_ok=True)

    run = RUNS / "prior-cpu"
    if not ensure_trained(run, "cpu", args.steps, args.until):
        print(f"training stopped early at --until {args.until}; run again to continue", file=sys.stderr)
        return 0
    reports = [training_report(run, "cpu")]
    fits = RUNS / "prior-fits"
    if not (RESULTS / "compression.json").is_file():
        hypnerf("eval", "compression", "--run", str(run), "--data", str(DATA), "--json", str(RESULTS / "compression.json"),
                "--objects", str(args.objects), "--fits", str(fits), "--fit-steps", str(FIT_STEPS))
    if not (RESULTS / "disentanglement.json").is_file():
        hypnerf("eval", "disentanglement", "--run", str(run), "--data", str(DATA), "--json", str(RESULTS / "disentanglement.json"),
                "--pairs", str(args.pairs))

    if not args.skip_ablation:
        # Without MRHE a step costs several times more, so the ablation trains for fewer steps; a
        # hash-grid prior trained for exactly as many steps is evaluated beside it, so the
        # comparison is at equal training (both are also in the training table and curve).
        ablation = RUNS / "prior-no-mrhe"
        matched = RUNS / f"prior-cpu-{args.ablation_steps}"
        if ensure_trained(ablation, "cpu-no-mrhe", args.ablation_steps, args.until) and ensure_trained(matched, "cpu", args.ablation_steps, args.until):
            reports += [training_report(ablation, "cpu-no-mrhe"), training_report(matched, "cpu")]
            if not (RESULTS / "compression_no_mrhe.json").is_file():
                hypnerf("eval", "compression", "--run", str(matched), "--data", str(DATA), "--json", str(matched / "compression.json"),
                        "--objects", str(args.objects), "--fits", str(fits), "--fit-steps", str(FIT_STEPS))
                hypnerf("eval", "compression", "--run", str(ablation), "--data", str(DATA), "--json", str(ablation / "compression.json"),
                        "--objects", str(args.objects), "--fits", str(fits), "--fit-steps", str(FIT_STEPS), "--ablation", "no-mrhe")
                result = json.loads((ablation / "compression.json").read_text())
                same = json.loads((matched / "compression.json").read_text())
                result["training_steps"] = args.ablation_steps
                result["hypernet_mrhe_same_steps"] = {**same["hypernet"], "psnr_gap_db": same["psnr_gap_db"]}
                write_result("compression_no_mrhe", result)
    plot_curves(reports, RESULTS / "training_curve.png")
    write_result("training", {"runs": reports, "curve_png": "benchmarks/results/training_curve.png"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
