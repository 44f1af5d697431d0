"""Inversion on unseen test-split chairs: the generalisation table (paper Table 1), PSNR against the
number of input views, TTO's speed against error, and poses (refinement of a wrong pose, search
for an unknown one).

Each stage writes ``benchmarks/results/<stage>.json`` (and a PNG) and is skipped when that file is
there. Plots are drawn with **matplotlib** (Agg backend). Every figure is at the dataset's 128x128
and scored with ``model.eval.metrics.image_quality`` (full and foreground PSNR, blank floors).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.bench_denoiser_selection import SHIPPED, train_command
from benchmarks.common import RESULTS, ROOT, hypnerf, write_result

RUN = ROOT / "runs" / "prior-cpu"
DATA = ROOT / "data" / "sh3d-chair-variants"
DENOISER = ROOT / "runs" / "denoise" / "denoiser"
# denoisers trained with TTO pairs besides the shipped one's pairs, each a further table row
SHIPPED_TRAIN = train_command(SHIPPED)
DENOISER_VARIANTS = {
    "tto_denoise_val_tto": ("denoiser-tto", SHIPPED_TRAIN),
    "tto_denoise_inputs": ("denoiser-tto", SHIPPED_TRAIN),
    "tto_denoise_rounds": ("denoiser-tto", SHIPPED_TRAIN),
    "tto_denoise_rounds3": ("denoiser-tto", SHIPPED_TRAIN),
    "tto_denoise_aug_tto": ("denoiser-tto-aug", "hypnerf train-denoiser --run runs/prior-cpu --data data/sh3d-chair-variants "
                            "--out runs/denoise/denoiser-tto-aug --steps 3000 --instances 0 --tto-objects 24 --tto-views 24 "
                            "--tto-data data/sh3d-chair-augmented"),
    "tto_denoise_inputs3": ("denoiser-tto-inputs3", train_command("denoiser-tto-inputs3")),
    "tto_denoise_mirror": ("denoiser-tto", SHIPPED_TRAIN),
}
# rows whose denoise-and-finetune settings differ from the defaults: their evaluation's arguments
# (the mirrored photo became the default after its row)
ROW_EVAL_ARGS = {"tto_denoise_rounds3": ("--denoise-rounds", "3"), "tto_denoise_mirror": ("--denoise-mirror",)}
# the row of the demo bundle's denoiser with the shipped denoise-and-finetune settings; its renders
# (beside TTO's) are copied next to the table
SHIPPED_DENOISE_ROW = "tto_denoise_mirror"
SHIPPED_DENOISE_FIGURE = RESULTS / "generalization_shipped_denoise.png"


def generalization(objects: int) -> None:
    """The table; a table made before the denoiser existed gains its ``tto_denoise`` row from a
    second run of ``tto`` and ``tto_denoise`` (TTO is seeded, so that run's ``tto`` row must
    reproduce the table's, which is checked and recorded)."""
    table = RESULTS / "generalization.json"
    denoiser = ["--denoiser", str(DENOISER)] if (DENOISER / "denoiser.safetensors").is_file() else []
    if not table.is_file():
        hypnerf("eval", "generalization", "--run", str(RUN), "--data", str(DATA), "--json", str(table), "--objects", str(objects), *denoiser)
        return
    report = json.loads(table.read_text())
    if "tto_denoise" not in report["rows"] and denoiser:
        _merge_denoise_row(report, "tto_denoise", DENOISER, RESULTS.parent.parent / "runs" / "generalization-denoise.json")
    for row, (folder, command) in DENOISER_VARIANTS.items():
        if row not in report["rows"] and (DENOISER.parent / folder / "denoiser.safetensors").is_file():
            _merge_denoise_row(report, row, DENOISER.parent / folder, RESULTS.parent.parent / "runs" / f"generalization-{row}.json",
                               ROW_EVAL_ARGS.get(row, ()))
            report.setdefault("denoiser_variants", {})[row] = {"train_command": command}
    side_figure = RESULTS.parent.parent / "runs" / f"generalization-{SHIPPED_DENOISE_ROW}.png"
    if SHIPPED_DENOISE_ROW in report["rows"] and side_figure.is_file():
        shutil.copyfile(side_figure, SHIPPED_DENOISE_FIGURE)
        report["shipped_denoise_row"] = SHIPPED_DENOISE_ROW
        report["shipped_denoise_figure"] = str(SHIPPED_DENOISE_FIGURE.relative_to(ROOT))
    table.write_text(json.dumps(report, indent=2) + "\n")


def _merge_denoise_row(report: dict, row: str, denoiser: Path, side: Path, eval_args: tuple[str, ...] = ()) -> None:
    """Add the ``tto_denoise`` row of a second run with ``denoiser`` to the table as ``row``; TTO is
    seeded, so that run's ``tto`` row must reproduce the table's (checked and recorded)."""
    if not side.is_file():
        hypnerf("eval", "generalization", "--run", str(RUN), "--data", str(DATA), "--json", str(side), "--objects", str(report["objects"]),
                "--rows", "tto,tto_denoise", "--denoiser", str(denoiser), *eval_args)
    extra = json.loads(side.read_text())
    drift = abs(extra["rows"]["tto"]["psnr_fg"] - report["rows"]["tto"]["psnr_fg"])
    if drift > 0.05:
        raise SystemExit(f"the second run's tto row differs from the table's by {drift:.3f} dB: rerun the whole table (delete {RESULTS / 'generalization.json'})")
    report["rows"][row] = extra["rows"]["tto_denoise"]
    suffix = "" if row == "tto_denoise" else f"_{row}"
    report[f"tto_denoise_command{suffix}"] = extra["command"]
    report[f"tto_reproduced_psnr_fg{suffix}"] = extra["rows"]["tto"]["psnr_fg"]
    report[f"tto_denoise_s{suffix}"] = extra.get("tto_denoise_s")
    report[f"denoise{suffix}"] = extra.get("denoise")  # the denoise-and-finetune settings (None: made before they were recorded)
    print(f"added {row} to the generalisation table (tto reproduced within {drift:.3f} dB)")


def _evaluation_subset(views, count: int):
    step = max(len(views.files) // count, 1)
    return views.subset(list(range(0, len(views.files), step))[:count])


def multiview(objects: int) -> None:
    """Full and foreground PSNR of TTO against the number of input views (the paper's appendix figure)."""
    if (RESULTS / "multiview.json").is_file():
        return
    from model.eval.generalization import GeneralizationConfig
    from model.eval.generalization import generalization as table

    rows = {}
    for views in (1, 3, 5, 10):
        cfg = GeneralizationConfig(objects=objects, input_views=views, rows=("tto",), grid_rows=0)
        report = table(RUN, DATA, cfg)
        rows[str(views)] = {**report["rows"]["tto"], "tto_s": report["tto_s"]}
        print(f"{views} views: {rows[str(views)]['psnr']:.2f} / {rows[str(views)]['psnr_fg']:.2f} dB", flush=True)
    write_result("multiview", {"rows": rows, "objects": objects, "floor_psnr": report["floor_psnr"], "floor_psnr_fg": report["floor_psnr_fg"],
                               "command": "python -m benchmarks.bench_inversion --stage multiview"})
    _plot(RESULTS / "multiview.png", [int(k) for k in rows], {"full": [r["psnr"] for r in rows.values()], "foreground": [r["psnr_fg"] for r in rows.values()]},
          "input views", "PSNR (dB)", "TTO on unseen chairs against the number of input views")


def _plot(path: Path, x, series: dict, xlabel: str, ylabel: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for name, ys in series.items():
        ax.plot(x, ys, marker="o", label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def speed(objects: int, eval_views: int = 12) -> None:
    """Held-out foreground PSNR against TTO wall time: codes snapshotted during the run are scored afterwards
    (scoring is not part of the timed run)."""
    if (RESULTS / "tto_speed.json").is_file():
        return
    from model.data.dataset import load_views
    from model.eval.field import render_views
    from model.eval.generalization import test_objects
    from model.eval.metrics import image_quality
    from model.nerf.renderer import RenderConfig
    from model.optimize.tto import TTOConfig, invert
    from model.prior.codes import generated_grid
    from model.prior.io import load_prior

    load_before = os.getloadavg()[0]  # the times mean most on an idle machine
    prior = load_prior(RUN)
    field = prior.net.cfg.field
    cfg = TTOConfig(patience=0)
    curves = []
    for object_id in test_objects(DATA, objects):
        held = load_views(DATA / object_id, "test").subset([0])
        evaluation = _evaluation_subset(load_views(DATA / object_id, "train"), eval_views)
        snaps = []
        result = invert(prior.net, prior.scene, held.images, held.c2w, held.cameras, cfg, snapshot=lambda e, s, c: snaps.append((e, s, c)))
        points = []
        for entry, shape, color in snaps:
            with torch.no_grad():
                params = prior.net.params_from_codes(shape[None], color[None])
            grid = generated_grid(params, field, prior.scene)
            rgb, opacity, _, _ = render_views(params, field, evaluation, RenderConfig(), grid, prior.scene)
            q = image_quality(rgb, evaluation.images, opacity)
            points.append({"step": entry["step"], "elapsed_s": entry["elapsed_s"], "psnr": q["psnr"], "psnr_fg": q["psnr_fg"]})
        curves.append({"id": object_id, "points": points, "wall_s": result.wall_s, "start": result.init,
                       "ms_per_step": 1000 * (points[-1]["elapsed_s"] - points[0]["elapsed_s"]) / max(points[-1]["step"] - points[0]["step"], 1)})
        print(object_id, points[0]["psnr_fg"], points[-1]["psnr_fg"], flush=True)
    steps = [p["step"] for p in curves[0]["points"]]
    mean_fg = [float(np.mean([c["points"][i]["psnr_fg"] for c in curves])) for i in range(len(steps))]
    mean_t = [float(np.mean([c["points"][i]["elapsed_s"] for c in curves])) for i in range(len(steps))]
    gain = mean_fg[-1] - mean_fg[0]
    reach = next((t for t, v in zip(mean_t, mean_fg) if v - mean_fg[0] >= 0.9 * gain), mean_t[-1]) if gain > 0 else None
    write_result("tto_speed", {
        "curve": [{"step": s, "elapsed_s": t, "psnr_fg": v} for s, t, v in zip(steps, mean_t, mean_fg)],
        "gain_db": gain, "time_to_90pct_gain_s": reach, "target_s": 30.0, "objects": len(curves),
        "start_s": mean_t[0], "start": {"init": cfg.init, "init_shapes": cfg.init_shapes, "init_rays": cfg.init_rays},
        "threads": torch.get_num_threads(), "load_average_before": load_before,
        "ms_per_step": float(np.mean([c["ms_per_step"] for c in curves])), "rays_per_step": cfg.rays_per_step,
        "evaluation_views": eval_views, "per_object": curves, "command": "python -m benchmarks.bench_inversion --stage speed",
    })
    _plot(RESULTS / "tto_speed.png", mean_t, {"foreground PSNR": mean_fg}, "TTO wall time (s, 2 cores)", "held-out PSNR (dB)",
          f"TTO speed against error ({len(curves)} unseen chairs)")


def poses(objects: int, eval_views: int = 12) -> None:
    """PSNR recovered by refining a wrong pose (5, 10, 20 degrees), and the unknown-pose search's success."""
    if (RESULTS / "poses.json").is_file():
        return
    from model.data.dataset import load_views
    from model.eval.field import render_views
    from model.eval.generalization import test_objects
    from model.eval.metrics import image_quality
    from model.nerf.renderer import RenderConfig
    from model.optimize.pose import perturb_pose, rotation_error_deg
    from model.optimize.tto import TTOConfig, invert
    from model.prior.io import load_prior

    prior = load_prior(RUN)
    field = prior.net.cfg.field
    rows: dict[str, list] = {}
    generator = torch.Generator().manual_seed(0)

    def score(result, evaluation) -> dict:
        rgb, opacity, _, _ = render_views(result.params, field, evaluation, RenderConfig(), result.grid, prior.scene)
        # the scalars only: image_quality also returns per-view lists and the foreground's definition
        return {k: v for k, v in image_quality(rgb, evaluation.images, opacity).items() if isinstance(v, float)}

    for object_id in test_objects(DATA, objects):
        held = load_views(DATA / object_id, "test").subset([0])
        evaluation = _evaluation_subset(load_views(DATA / object_id, "train"), eval_views)
        exact = invert(prior.net, prior.scene, held.images, held.c2w, held.cameras, TTOConfig())
        rows.setdefault("exact", []).append(score(exact, evaluation))
        for degrees in (5, 10, 20):
            wrong = perturb_pose(held.c2w[0], degrees, generator, translation=0.02 * degrees / 10)[None]
            for refine in (False, True):
                result = invert(prior.net, prior.scene, held.images, wrong, held.cameras, TTOConfig(refine_pose=refine))
                q = score(result, evaluation)
                q["final_error_deg"] = float(rotation_error_deg(result.c2w[0], held.c2w[0]))
                rows.setdefault(f"{degrees}deg_{'refined' if refine else 'fixed'}", []).append(q)
        unknown = invert(prior.net, prior.scene, held.images, None, held.cameras, TTOConfig())
        q = score(unknown, evaluation)
        q["final_error_deg"] = float(rotation_error_deg(unknown.c2w[0], held.c2w[0]))
        rows.setdefault("unknown", []).append(q)
        print(object_id, {k: (round(v[-1]["psnr_fg"], 2), round(v[-1].get("final_error_deg", 0.0), 1)) for k, v in rows.items()}, flush=True)
    summary = {k: {m: float(np.mean([r[m] for r in v])) for m in v[0]} for k, v in rows.items()}
    summary["unknown"]["success_rate"] = float(np.mean([r["final_error_deg"] < 15.0 for r in rows["unknown"]]))
    write_result("poses", {"rows": summary, "objects": objects, "evaluation_views": eval_views, "per_object": rows,
                           "command": "python -m benchmarks.bench_inversion --stage poses"})


def start(objects: int) -> None:
    """TTO's nearest-instance start in two rounds (every shape by silhouette, then the colour
    variants of the best few) against scoring every instance: the instance each picks and the
    time each takes, on the generalisation table's test objects and input views. TTO is seeded and
    the start draws no random numbers, so where the two agree the whole run is the same."""
    if (RESULTS / "tto_start.json").is_file():
        return
    from dataclasses import replace

    from model.data.dataset import load_views
    from model.eval.generalization import test_objects
    from model.optimize.pose import PixelBank
    from model.optimize.tto import TTOConfig, nearest_instance
    from model.prior.io import load_prior

    prior = load_prior(RUN)
    net, cfg = prior.net, TTOConfig()
    coarse = replace(cfg.render, samples_per_ray=cfg.init_samples_per_ray)
    rows = []
    for object_id in test_objects(DATA, objects):
        held = load_views(DATA / object_id, "test").subset([0])
        batch = PixelBank(held.images, held.cameras, "cpu").sample(cfg.init_rays, held.c2w, torch.Generator().manual_seed(cfg.seed))
        picks, times = {}, {}
        for name, shortlist in (("all_instances", 0), ("two_rounds", cfg.init_shapes)):
            began = time.perf_counter()
            picks[name] = nearest_instance(net, net.cfg.field, prior.scene, batch, coarse, shortlist, silhouette=True)
            times[name] = time.perf_counter() - began
        rows.append({"id": object_id, "instance": {k: prior.instances[v]["id"] for k, v in picks.items()},
                     "same": picks["all_instances"] == picks["two_rounds"], "seconds": times})
        print(object_id, rows[-1]["same"], {k: round(v, 2) for k, v in times.items()}, flush=True)
    write_result("tto_start", {
        "objects": len(rows), "agreement": float(np.mean([r["same"] for r in rows])),
        "seconds": {k: float(np.mean([r["seconds"][k] for r in rows])) for k in ("all_instances", "two_rounds")},
        "shortlist_shapes": cfg.init_shapes, "instances": net.instances, "shapes": int(net.shape_index.max()) + 1,
        "threads": torch.get_num_threads(), "per_object": rows, "command": "python -m benchmarks.bench_inversion --stage start",
    })


def mirror(objects: int) -> None:
    """Single-view TTO with the input's mirrored virtual view (``TTOConfig(mirror=True)``; chairs are
    left-right symmetric) on the generalisation table's objects and views, against the table's own
    ``tto`` row (same objects, input views and seeds)."""
    if (RESULTS / "tto_mirror.json").is_file():
        return
    from model.eval.generalization import GeneralizationConfig
    from model.eval.generalization import generalization as table
    from model.optimize.tto import TTOConfig

    reference = json.loads((RESULTS / "generalization.json").read_text())
    report = table(RUN, DATA, GeneralizationConfig(objects=reference["objects"], rows=("tto",), grid_rows=0, tto=TTOConfig(mirror=True)))
    mirrored, plain = report["rows"]["tto"], reference["rows"]["tto"]
    print(f"TTO {plain['psnr']:.2f} / {plain['psnr_fg']:.2f} dB; with the mirrored view {mirrored['psnr']:.2f} / {mirrored['psnr_fg']:.2f} dB", flush=True)
    write_result("tto_mirror", {"rows": {"tto": plain, "tto_mirror": {**mirrored, "tto_s": report["tto_s"]}}, "objects": report["objects"],
                                "tto_s": reference["tto_s"], "floor_psnr": report["floor_psnr"], "floor_psnr_fg": report["floor_psnr_fg"],
                                "reference": "the tto row of benchmarks/results/generalization.json (same objects, input views and seeds)",
                                "command": "python -m benchmarks.bench_inversion --stage mirror"})


STAGES = {"generalization": generalization, "multiview": multiview, "speed": speed, "poses": poses, "start": start, "mirror": mirror}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stage", choices=[*STAGES, "all"], default="all")
    parser.add_argument("--objects", type=int, help="test objects per stage (default: 11 for the table, 4 for the rest)")
    args = parser.parse_args()
    for name, stage in STAGES.items():
        if args.stage in (name, "all"):
            start = time.perf_counter()
            stage(args.objects or (11 if name in ("generalization", "start") else 4))
            print(f"stage {name}: {time.perf_counter() - start:.0f} s", flush=True)


if __name__ == "__main__":
    main()
