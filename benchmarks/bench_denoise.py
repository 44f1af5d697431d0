"""Denoise and finetune on the Sweet Home 3D chair prior (paper section 3.1 step 2, appendix table).

Stages (the training resumes from its checkpoint and is skipped once the denoiser exists):

1. ``hypnerf train-denoiser`` on renders of ``runs/prior-cpu``; its loss curve and time.
2. The denoiser alone on held-out views (test frames) of training instances: full and foreground
   PSNR of the raw render and of the denoised render against the ground truth.
3. Test-split objects (never seen in training): TTO from one held-out view, then the denoiser on
   the renders of the nearest training instance and of the TTO NeRF, and denoise-and-finetune of
   the TTO NeRF, scored at every third training frame of the object (poses nobody denoised).
4. Denoise-and-finetune of training instances' own NeRFs: PSNR at their test frames (not among
   the denoised poses) before and after, Chamfer distance to the ground-truth mesh before and
   after (and between the two meshes), and the time it takes.

Writes ``benchmarks/results/denoise.json`` and ``denoise.png`` (per object: ground truth, raw
render, denoised render, finetuned NeRF at a few poses).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import torch
import trimesh

from benchmarks.common import RESULTS, ROOT, hypnerf, write_result

RUN = ROOT / "runs" / "prior-cpu"
DATA = ROOT / "data" / "sh3d-chair-variants"
# the shipped denoiser: pairs of the prior's renders of training instances and TTO results of
# validation objects (a denoiser on the prior's renders alone gains nothing on unseen chairs)
DENOISER = ROOT / "runs" / "denoise" / "denoiser-tto"
TRAIN_ARGS = ("--instances", "0", "--tto-objects", "12", "--tto-views", "24")


def train_arguments(steps: int) -> list[str]:
    return ["train-denoiser", "--run", str(RUN.relative_to(ROOT)), "--data", str(DATA.relative_to(ROOT)),
            "--out", str(DENOISER.relative_to(ROOT)), "--steps", str(steps), *TRAIN_ARGS]


def ensure_denoiser(steps: int, until: int | None) -> bool:
    """Train (or continue) the denoiser; returns whether it is finished."""
    if (DENOISER / "denoiser.json").is_file():
        return True
    args = train_arguments(steps)
    if (DENOISER / "checkpoint" / "state.json").is_file():
        args.append("--resume")
    if until:
        args += ["--until", str(until)]
    hypnerf(*args)
    return (DENOISER / "denoiser.json").is_file()


def quality(rgb: torch.Tensor, images: torch.Tensor, opacity: torch.Tensor) -> dict:
    """The project's full and foreground PSNR with their floors, plus the foreground PSNR on the
    ground truth's own mask: the project's foreground also counts pixels the render covers, so
    a render that drops haze loses easy near-white pixels from it and scores lower there."""
    from model.eval.metrics import image_quality, psnr
    from model.nerf.images import composite_over

    scores = image_quality(rgb, images, opacity)
    row = {k: scores[k] for k in ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg")}
    row["psnr_fg_gt_mask"] = psnr(rgb, composite_over(images), images[..., 3] > 0)
    return row


def _mean(rows: list[dict], key: str) -> dict:
    keys = rows[0][key].keys()
    return {k: sum(r[key][k] for r in rows) / len(rows) for k in keys}


class Bench:
    def __init__(self):
        from model.data.dataset import load_index
        from model.denoise.io import load_denoiser
        from model.prior.io import load_prior

        self.prior = load_prior(RUN)
        self.field = self.prior.net.cfg.field
        self.denoiser, self.meta = load_denoiser(DENOISER)
        self.index = load_index(DATA)

    def renders(self, params, grid, views):
        from model.eval.field import render_views
        from model.nerf.renderer import RenderConfig

        rgb, opacity, _, _ = render_views(params, self.field, views, RenderConfig(), grid, self.prior.scene)
        return rgb, opacity

    def raw_and_denoised(self, rgb, opacity, views) -> tuple[dict, dict, torch.Tensor]:
        from model.denoise.vqvae import denoise_renders
        from model.nerf.images import composite_over

        rgba = denoise_renders(self.denoiser, rgb, opacity)
        denoised = composite_over(rgba)
        return quality(rgb, views.images, opacity), quality(denoised, views.images, rgba[..., 3]), denoised

    def chamfer(self, params, grid, views) -> tuple[float, trimesh.Trimesh]:
        from model.eval.metrics import mesh_chamfer
        from model.nerf.mesh import field_mesh

        mesh = field_mesh(params, self.field, grid, self.prior.scene, 128)
        reference = trimesh.load(views.mesh_path, force="mesh")
        return mesh_chamfer(mesh, reference, unit=self.prior.scene.longest_side), mesh

    def denoise_finetune(self, params, grid, inputs=None):
        from model.denoise.finetune import (
            DenoiseConfig,
            denoise_and_finetune,
            ring_poses,
        )
        from model.nerf import config
        from model.nerf.rays import Intrinsics

        camera = config.from_dict(Intrinsics, self.prior.meta["camera"])
        return denoise_and_finetune(params, self.field, self.prior.scene, self.denoiser, ring_poses(), camera, DenoiseConfig(), grid=grid, inputs=inputs)


def held_out_training_views(bench: Bench, count: int) -> dict:
    """Stage 2: the denoiser on the test frames of training instances, rendered from their own codes."""
    from model.data.dataset import load_views
    from model.prior.codes import generate, generated_grid
    from model.train.denoiser import spread

    rows = []
    for n in spread(count, len(bench.prior.instances)):
        views = load_views(DATA / bench.prior.instances[n]["id"], "test")
        params = generate(bench.prior.net, n)
        rgb, opacity = bench.renders(params, generated_grid(params, bench.field, bench.prior.scene), views)
        raw, denoised, _ = bench.raw_and_denoised(rgb, opacity, views)
        rows.append({"id": bench.prior.instances[n]["id"], "raw": raw, "denoised": denoised})
        print(f"  {rows[-1]['id']}: raw {raw['psnr']:.2f} / {raw['psnr_fg']:.2f} dB, denoised {denoised['psnr']:.2f} / {denoised['psnr_fg']:.2f} dB")
    return {"instances": rows, "raw": _mean(rows, "raw"), "denoised": _mean(rows, "denoised"), "views_per_instance": 12}


def finetune_training_instances(bench: Bench, count: int, picture: list) -> dict:
    """Stage 4: denoise-and-finetune of training instances' own NeRFs."""
    from model.data.dataset import load_views
    from model.eval.metrics import mesh_chamfer
    from model.nerf.images import composite_over
    from model.prior.codes import generate, generated_grid
    from model.train.denoiser import spread

    rows = []
    for n in spread(count, len(bench.prior.instances)):
        views = load_views(DATA / bench.prior.instances[n]["id"], "test")
        params = generate(bench.prior.net, n)
        grid = generated_grid(params, bench.field, bench.prior.scene)
        rgb, opacity = bench.renders(params, grid, views)
        chamfer_before, mesh_before = bench.chamfer(params, grid, views)
        result = bench.denoise_finetune(params, grid)
        rgb_after, opacity_after = bench.renders(result.params, result.grid, views)
        chamfer_after, mesh_after = bench.chamfer(result.params, result.grid, views)
        _, _, denoised = bench.raw_and_denoised(rgb, opacity, views)
        row = {
            "id": bench.prior.instances[n]["id"],
            "before": quality(rgb, views.images, opacity),
            "after": quality(rgb_after, views.images, opacity_after),
            "chamfer_before": chamfer_before, "chamfer_after": chamfer_after,
            "chamfer_before_to_after": mesh_chamfer(mesh_before, mesh_after, unit=bench.prior.scene.longest_side),
            "timings_s": result.timings,
        }
        rows.append(row)
        print(f"  {row['id']}: held-out {row['before']['psnr']:.2f} / {row['before']['psnr_fg']:.2f} -> {row['after']['psnr']:.2f} / "
              f"{row['after']['psnr_fg']:.2f} dB, Chamfer {chamfer_before:.4f} -> {chamfer_after:.4f}, {result.timings['total_s']:.1f} s")
        if len(picture) < 4:
            target = composite_over(views.images)
            picture.append([image for v in (0, 5, 10) for image in (target[v], rgb[v], denoised[v], rgb_after[v])])
    return {
        "instances": rows, "before": _mean(rows, "before"), "after": _mean(rows, "after"),
        "chamfer_before": sum(r["chamfer_before"] for r in rows) / len(rows), "chamfer_after": sum(r["chamfer_after"] for r in rows) / len(rows),
        "chamfer_before_to_after": sum(r["chamfer_before_to_after"] for r in rows) / len(rows),
        "total_s": sum(r["timings_s"]["total_s"] for r in rows) / len(rows),
    }


def test_objects(bench: Bench, count: int, picture: list) -> dict:
    """Stage 3: TTO on unseen objects, then the denoiser and denoise-and-finetune."""
    from model.data.dataset import load_views
    from model.nerf.images import composite_over
    from model.optimize.tto import TTOConfig, invert
    from model.prior.codes import generate, generated_grid
    from model.train.denoiser import spread

    ids = bench.index.ids("test")
    rows = []
    for k in spread(count, len(ids)):
        object_id = ids[k]
        held = load_views(DATA / object_id, "test")
        evaluation = load_views(DATA / object_id, "train").subset(slice(0, None, 3))
        inputs = held.subset([0])
        start = time.perf_counter()
        tto = invert(bench.prior.net, bench.prior.scene, inputs.images, inputs.c2w, inputs.cameras, TTOConfig())
        tto_s = time.perf_counter() - start
        nearest = int(tto.init.split(":")[1]) if tto.init.startswith("nearest:") else None
        row = {"id": object_id, "tto_s": tto_s, "tto_init": tto.init}
        if nearest is not None:
            params = generate(bench.prior.net, nearest)
            rgb, opacity = bench.renders(params, generated_grid(params, bench.field, bench.prior.scene), evaluation)
            row["nearest_raw"], row["nearest_denoised"], _ = bench.raw_and_denoised(rgb, opacity, evaluation)
        rgb, opacity = bench.renders(tto.params, tto.grid, evaluation)
        row["tto_raw"], row["tto_denoised_image"], denoised = bench.raw_and_denoised(rgb, opacity, evaluation)
        row["tto_chamfer"], _ = bench.chamfer(tto.params, tto.grid, evaluation)
        result = bench.denoise_finetune(tto.params, tto.grid, (inputs.images, tto.c2w, inputs.cameras))
        rgb_after, opacity_after = bench.renders(result.params, result.grid, evaluation)
        row["tto_denoise_finetune"] = quality(rgb_after, evaluation.images, opacity_after)
        row["tto_denoise_finetune_chamfer"], _ = bench.chamfer(result.params, result.grid, evaluation)
        row["denoise_finetune_s"] = result.timings
        rows.append(row)
        print(f"  {object_id}: TTO {row['tto_raw']['psnr']:.2f} / {row['tto_raw']['psnr_fg']:.2f} dB, denoised image "
              f"{row['tto_denoised_image']['psnr']:.2f} / {row['tto_denoised_image']['psnr_fg']:.2f}, D&F {row['tto_denoise_finetune']['psnr']:.2f} / "
              f"{row['tto_denoise_finetune']['psnr_fg']:.2f}; Chamfer {row['tto_chamfer']:.4f} -> {row['tto_denoise_finetune_chamfer']:.4f}")
        if len(picture) < 8:
            target = composite_over(evaluation.images)
            picture.append([composite_over(inputs.images)[0]] + [image for v in (2, 12, 22) for image in (target[v], rgb[v], denoised[v], rgb_after[v])])
    summary = {key: _mean([r for r in rows if key in r], key) for key in ("nearest_raw", "nearest_denoised", "tto_raw", "tto_denoised_image", "tto_denoise_finetune")
               if any(key in r for r in rows)}
    summary["tto_chamfer"] = sum(r["tto_chamfer"] for r in rows) / len(rows)
    summary["tto_denoise_finetune_chamfer"] = sum(r["tto_denoise_finetune_chamfer"] for r in rows) / len(rows)
    return {"objects": rows, "mean": summary, "input": "test frame 0", "evaluated_at": "every third training frame (31 views)"}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=3000, help="denoiser training steps")
    parser.add_argument("--until", type=int, help="train only up to this step now (resume later)")
    parser.add_argument("--held-out", type=int, default=6, help="training instances whose test frames are denoised")
    parser.add_argument("--finetune", type=int, default=4, help="training instances denoised and finetuned")
    parser.add_argument("--objects", type=int, default=3, help="test-split objects inverted")
    args = parser.parse_args(argv)
    if not ensure_denoiser(args.steps, args.until):
        print("denoiser training stopped early; run again to continue")
        return 0
    from model.eval.prior import save_grid

    bench = Bench()
    summary = bench.meta["summary"]
    history = [{k: h[k] for k in h if k in ("step", "loss", "mse", "train_psnr", "perplexity_top", "perplexity_bottom", "elapsed_s") or k.startswith("val_")}
               for h in json.loads((DENOISER / "history.json").read_text())]
    print("held-out views of training instances:")
    held = held_out_training_views(bench, args.held_out)
    picture: list = []
    print("denoise and finetune of training instances:")
    finetuned = finetune_training_instances(bench, args.finetune, picture)
    print("test-split objects:")
    unseen = test_objects(bench, args.objects, picture)
    save_grid(RESULTS / "denoise.png", picture)
    from model.denoise.finetune import DenoiseConfig
    from model.nerf import config

    write_result("denoise", {
        "denoise": config.to_dict(DenoiseConfig()),
        "command": "python -m benchmarks.bench_denoise " + " ".join(sys.argv[1:] if argv is None else argv),
        "train_command": "hypnerf " + " ".join(train_arguments(summary["steps"])),
        "denoiser": {**bench.meta["denoiser"], "parameters": summary["parameters"]},
        "training": {"steps": summary["steps"], "pairs": summary["pairs"], "validation_pairs": summary["validation_pairs"], "wall_s": summary["wall_s"],
                     "threads": summary["threads"], "history": history[:: max(1, len(history) // 60)] + history[-1:]},
        "held_out_training_views": held,
        "denoise_finetune_training_instances": finetuned,
        "test_objects": unseen,
        "figure": "benchmarks/results/denoise.png: per row ground truth, raw render, denoised render, finetuned NeRF at three poses "
                  "(test-object rows start with the input view)",
        "foreground": "psnr_fg: pixels where the ground-truth alpha > 0 or the render's opacity >= 1/255 (the project's); "
                      "psnr_fg_gt_mask: pixels where the ground-truth alpha > 0",
    })
    return 0


if __name__ == "__main__":
    sys.exit(main())
