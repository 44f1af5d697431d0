"""``hypnerf train-query``, ``hypnerf text``, ``hypnerf sample`` and the query network's ``hypnerf eval``
subcommands (``retrieval``, ``text-to-nerf``, ``sampling``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _positive(name: str, value: int) -> None:
    if value < 1:
        raise ValueError(f"--{name} must be at least 1, got {value}")


def _command() -> str:
    return "hypnerf " + " ".join(sys.argv[1:])


def _write_json(path: str | Path, data: dict) -> None:
    from model.cli.main import _write_json as write_report

    write_report(str(path), data)


# ---------------------------------------------------------------------------------------------
# train-query


def register_train(parser: argparse.ArgumentParser) -> None:
    from model.prior.query import HEADS
    from model.train.query import QueryTrainConfig

    defaults = QueryTrainConfig()
    parser.add_argument("--run", required=True, help="prior run folder written by `hypnerf train`")
    parser.add_argument("--data", required=True, help="the dataset the prior was trained on")
    parser.add_argument("--out", help="folder for the query network (default RUN/query)")
    parser.add_argument("--views", type=int, default=defaults.views_per_instance, help="training renders embedded per instance")
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--batch", type=int, default=defaults.batch)
    parser.add_argument("--lr", type=float, default=defaults.lr)
    parser.add_argument("--text-fraction", type=float, default=defaults.text_fraction, help="share of each batch that is caption embeddings")
    parser.add_argument("--image-embedder", default=defaults.image_embedder, choices=["efficientnet-lite0", "clip"])
    parser.add_argument("--text-embedder", default=defaults.text_embedder, choices=["minilm", "clip", ""], help="'' trains an image-only network")
    parser.add_argument("--head", default=defaults.query.head, choices=list(HEADS),
                        help="codebook: attention over the codebook, trained as classification; regression: the paper's L2 onto the codes; "
                             "shape-codebook: the shape classified, the colour code regressed")
    parser.add_argument("--composed", type=int, default=defaults.composed_per_pair,
                        help="composed captions per (shape, colour none of its instances wears), aimed at that shape with another "
                             f"instance's colour code (default {defaults.composed_per_pair}; 0: own captions only)")
    parser.add_argument("--vocabulary", type=int, default=defaults.vocabulary_captions,
                        help="captions naming the colour by a word of the XKCD survey's colour names filed under it, per instance and "
                             f"per composed pair (default {defaults.vocabulary_captions}; 0: palette and training colour words only)")
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.set_defaults(func=cmd_train)


def cmd_train(args) -> int:
    from model.nerf.device import default_device
    from model.train.query import QueryTrainConfig, train_query

    for name in ("views", "steps", "batch"):
        _positive(name, getattr(args, name))
    from model.prior.query import QueryConfig

    cfg = QueryTrainConfig(query=QueryConfig(head=args.head), image_embedder=args.image_embedder, text_embedder=args.text_embedder, views_per_instance=args.views,
                           steps=args.steps, batch=args.batch, lr=args.lr, text_fraction=args.text_fraction, composed_per_pair=args.composed,
                           vocabulary_captions=args.vocabulary, seed=args.seed)
    out = Path(args.out) if args.out else Path(args.run) / "query"
    summary = train_query(Path(args.run), Path(args.data), out, cfg, default_device())
    validation = summary["validation"]
    held_out = f"; held-out views top-1 {100 * validation['top1']:.1f}% of {validation['queries']}" if validation else ""
    print(f"query network in {out}: {summary['instances']} instances, {summary['views_per_instance']} views and "
          f"{summary['captions']} captions, final loss {summary['final_loss']:.4f}{held_out} ({summary['wall_s']:.0f} s)")
    return 0


# ---------------------------------------------------------------------------------------------
# text


def register_text(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("prompt", help='what to make, e.g. "a red leather armchair"')
    parser.add_argument("--run", required=True, help="prior run folder written by `hypnerf train`")
    parser.add_argument("--query", help="query network folder written by `hypnerf train-query` (default RUN/query)")
    parser.add_argument("--out", required=True, help="folder for nerf.safetensors/.json (codes, timings), renders/, turntable.gif and mesh.glb")
    parser.add_argument("--raw", action="store_true", help="use Delta's codes as they are instead of the nearest codebook entries (may decode to a blend)")
    parser.add_argument("--frames", type=int, default=24, help="turntable frames")
    parser.add_argument("--res", type=int, default=128, help="render resolution")
    parser.add_argument("--mesh-resolution", type=int, default=128)
    parser.set_defaults(func=cmd_text)


def nerf_of_codes(prior, shape, color, res: int):
    """The NeRF of codes ``[1, S]``, ``[1, C]``, its occupancy grid, a camera of ``res`` pixels, its
    first render ``[H, W, 3]`` at the first evaluation pose, and what each step took (ms)."""
    import time

    import torch

    from model.data.cameras import CAMERA_ANGLE_X, evaluation_poses
    from model.nerf.rays import Intrinsics
    from model.nerf.renderer import RenderConfig, render_image
    from model.prior.codes import generated_grid

    start = time.perf_counter()
    with torch.no_grad():
        params = prior.net.params_from_codes(shape, color)
    made = time.perf_counter()
    grid = generated_grid(params, prior.net.cfg.field, prior.scene)
    gridded = time.perf_counter()
    camera = Intrinsics.from_fov(res, res, CAMERA_ANGLE_X)
    first = render_image(params, prior.net.cfg.field, torch.as_tensor(evaluation_poses()[0]).float(), camera, RenderConfig(), scene=prior.scene, grid=grid)["rgb"]
    timings = {"hypernetwork_ms": 1000 * (made - start), "occupancy_grid_ms": 1000 * (gridded - made), "first_render_ms": 1000 * (time.perf_counter() - gridded)}
    return params, grid, camera, first, timings


def cmd_text(args) -> int:
    import time

    from model.nerf.device import default_device
    from model.prior.outputs import write_outputs
    from model.prior.query import QueryPipeline, nearest_instances

    for name in ("frames", "res", "mesh_resolution"):
        _positive(name.replace("_", "-"), getattr(args, name))
    query = Path(args.query) if args.query else Path(args.run) / "query"
    start = time.perf_counter()
    pipeline = QueryPipeline.from_runs(Path(args.run), query, default_device())
    loaded = time.perf_counter()
    embedding, read = pipeline.text_embedding(args.prompt)
    embedded = time.perf_counter()
    raw_shape, raw_color = pipeline.codes(embedding, snap=False)
    shape, color = (raw_shape, raw_color) if args.raw else pipeline.codes(embedding, snap=True, colour=read.palette)
    coded = time.perf_counter()
    out = Path(args.out)
    timings = {"load_s": loaded - start, "embedding_ms": 1000 * (embedded - loaded), "query_ms": 1000 * (coded - embedded)}
    prior = pipeline.prior
    params, grid, camera, _, made = nerf_of_codes(prior, shape, color, args.res)
    timings.update(made)
    nearest = nearest_instances(pipeline.net, raw_shape, raw_color, pipeline.shape_book, pipeline.color_book, k=3)[0].tolist()
    result = {
        "prompt": args.prompt,
        "read_as": read.prompt,
        "snapped": not args.raw,
        "nearest_instances": [prior.instances[i]["id"] for i in nearest],
        "shape_code": shape[0].tolist(),
        "color_code": color[0].tolist(),
        "timings": timings,
        "command": _command(),
    }
    write_outputs(out, params, prior.net.cfg.field, grid, prior.scene, camera, extra=result, turntable_frames=args.frames, mesh_resolution=args.mesh_resolution)
    if read.name:
        print(f"read the colour {read.name!r} as {read.palette}: {read.prompt!r}")
    print(f"{args.prompt!r}: nearest training instances {', '.join(result['nearest_instances'])}; "
          f"NeRF, renders, turntable.gif and mesh.glb in {out} (embedding {timings['embedding_ms']:.0f} ms, Delta {timings['query_ms']:.1f} ms, "
          f"hypernetwork {timings['hypernetwork_ms']:.0f} ms, first render {timings['first_render_ms']:.0f} ms)")
    return 0


# ---------------------------------------------------------------------------------------------
# sample


def register_sample(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--run", required=True, help="prior run folder written by `hypnerf train`")
    parser.add_argument("--n", type=int, required=True, help="how many samples")
    parser.add_argument("--out", required=True, help="folder for sample_<k>/ (NeRF, renders, turntable, mesh), grid.png and samples.json")
    parser.add_argument("--temperature", type=float, default=1.0, help="scale of each mixture component's spread (1: the fitted density)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=12, help="turntable frames per sample")
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--mesh-resolution", type=int, default=96)
    parser.set_defaults(func=cmd_sample)


def cmd_sample(args) -> int:
    import torch

    from model.eval.query import save_rows
    from model.nerf.device import default_device
    from model.prior.io import load_prior
    from model.prior.outputs import write_outputs
    from model.prior.sampling import CodeDensity, DensityConfig, nearest_code_distance

    for name in ("n", "frames", "res", "mesh_resolution"):
        _positive(name.replace("_", "-"), getattr(args, name))
    prior = load_prior(Path(args.run), default_device())
    with torch.no_grad():
        shapes = prior.net.shape_codes.weight.detach()
        _, colors = prior.net.codes(torch.arange(len(prior.instances), device=prior.device))
    density = CodeDensity.fit(shapes, colors, DensityConfig(seed=args.seed))
    drawn_shape, drawn_color = density.sample(args.n, seed=args.seed, temperature=args.temperature)
    shape_rel, shape_near = nearest_code_distance(drawn_shape, shapes.cpu())
    color_rel, color_near = nearest_code_distance(drawn_color, colors.cpu())
    out = Path(args.out)
    rows, firsts = [], []
    first_of_shape = {inst["shape_index"]: inst["id"] for inst in reversed(prior.instances)}
    for k in range(args.n):
        folder = out / f"sample_{k:03d}"
        params, grid, camera, first, _ = nerf_of_codes(prior, drawn_shape[k : k + 1].to(prior.device), drawn_color[k : k + 1].to(prior.device), args.res)
        firsts.append(first.cpu())
        row = {"sample": k, "folder": str(folder), "shape_distance": float(shape_rel[k]), "colour_distance": float(color_rel[k]),
               "nearest_shape": first_of_shape[int(shape_near[k])], "nearest_colour": prior.instances[int(color_near[k])]["id"]}
        write_outputs(folder, params, prior.net.cfg.field, grid, prior.scene, camera, extra=row, turntable_frames=args.frames, mesh_resolution=args.mesh_resolution)
        rows.append(row)
    save_rows(out / "grid.png", [tuple(firsts[i : i + 6]) for i in range(0, len(firsts), 6)])
    (out / "samples.json").write_text(json.dumps({
        "density": density.to_json(), "temperature": args.temperature, "seed": args.seed, "samples": rows,
        "distance_unit": "the codebook's median nearest-neighbour spacing", "command": _command(),
    }, indent=2))
    print(f"{args.n} samples in {out}: median distance to the nearest training code {float(shape_rel.median()):.2f} (shape), "
          f"{float(color_rel.median()):.2f} (colour) codebook spacings; grid {out / 'grid.png'}")
    return 0


# ---------------------------------------------------------------------------------------------
# eval retrieval | text-to-nerf | sampling


def register_eval_query(eval_sub) -> None:
    """The query network's subcommands of ``hypnerf eval``."""
    ret = eval_sub.add_parser("retrieval", help="retrieve training instances from unposed views at new poses (paper Table 3), clean and cluttered")
    ret.add_argument("--run", required=True, help="prior run folder")
    ret.add_argument("--data", required=True, help="the dataset the prior was trained on")
    ret.add_argument("--query", help="query network folder (default RUN/query)")
    ret.add_argument("--json", required=True, help="where to write the report")
    ret.add_argument("--grid", help="PNG of example queries: clean | cluttered | GrabCut from the border | GrabCut from a box (default: beside --json)")
    ret.add_argument("--views", type=int, default=2, help="new random views per instance")
    ret.add_argument("--no-clutter", action="store_true", help="only clean queries")
    ret.add_argument("--seed", type=int, default=0)
    ret.set_defaults(func=cmd_eval_retrieval)
    txt = eval_sub.add_parser("text-to-nerf", help="NeRFs from held-out prompts: dominant colour and type accuracy")
    txt.add_argument("--run", required=True)
    txt.add_argument("--data", required=True)
    txt.add_argument("--query", help="query network folder (default RUN/query)")
    txt.add_argument("--json", required=True)
    txt.add_argument("--grid", help="PNG grid of prompt -> renders (default: beside --json)")
    txt.add_argument("--prompts", type=int, default=40)
    txt.add_argument("--raw", action="store_true", help="Delta's codes as they are (no snapping to the codebook)")
    txt.add_argument("--no-colour-words", action="store_true", help="embed the prompts as they are (no colour lexicon)")
    txt.add_argument("--seed", type=int, default=0)
    txt.set_defaults(func=cmd_eval_text)
    smp = eval_sub.add_parser("sampling", help="unconditional samples and interpolation paths: distance to training codes, validity proxies")
    smp.add_argument("--run", required=True)
    smp.add_argument("--json", required=True)
    smp.add_argument("--grid", help="PNG of the samples (default: beside --json)")
    smp.add_argument("--interpolation-grid", help="PNG of the interpolation paths (default: beside --json)")
    smp.add_argument("--samples", type=int, default=12)
    smp.add_argument("--temperature", type=float, default=1.0)
    smp.add_argument("--seed", type=int, default=0)
    smp.set_defaults(func=cmd_eval_sampling)
    tto = eval_sub.add_parser("query-tto", help="TTO of unseen test objects started from the query network's guess vs the mean code vs the nearest instance")
    tto.add_argument("--run", required=True)
    tto.add_argument("--data", required=True)
    tto.add_argument("--query", help="query network folder (default RUN/query)")
    tto.add_argument("--json", required=True)
    tto.add_argument("--objects", type=int, default=3, help="test objects (distinct shapes first)")
    tto.add_argument("--steps", type=int, default=150, help="TTO steps per start (no early stopping, so every start runs as long)")
    tto.set_defaults(func=cmd_eval_query_tto)


def _pipeline(args):
    from model.nerf.device import default_device
    from model.prior.query import QueryPipeline

    query = Path(args.query) if args.query else Path(args.run) / "query"
    return QueryPipeline.from_runs(Path(args.run), query, default_device())


def _beside(json_path: str, given: str | None, suffix: str) -> Path:
    return Path(given) if given else Path(json_path).with_name(Path(json_path).stem + suffix)


def cmd_eval_retrieval(args) -> int:
    from model.eval.query import retrieval

    _positive("views", args.views)
    grid = _beside(args.json, args.grid, ".png")
    report = retrieval(_pipeline(args), Path(args.data), views_per_instance=args.views, seed=args.seed, clutter_queries=not args.no_clutter, grid_png=grid)
    report["command"] = _command()
    _write_json(args.json, report)
    lines = [f"{report['queries']} queries of {report['instances']} instances: top-1 {100 * report['top1']:.1f}%, top-3 {100 * report['top3']:.1f}%, "
             f"shape top-1 {100 * report['shape_top1']:.1f}% (Delta's codes, clean views)"]
    for condition, methods in report["conditions"].items():
        lines.append(f"  {condition:<22} " + "  ".join(f"{m}: {100 * r['top1']:.1f}/{100 * r['top3']:.1f}%" for m, r in methods.items()))
    print("\n".join(lines))
    return 0


def cmd_eval_text(args) -> int:
    from model.eval.query import text_to_nerf

    _positive("prompts", args.prompts)
    grid = _beside(args.json, args.grid, ".png")
    report = text_to_nerf(_pipeline(args), Path(args.data), prompts=args.prompts, seed=args.seed, snap=not args.raw,
                          read_colours=not args.no_colour_words, grid_png=grid)
    report["command"] = _command()
    _write_json(args.json, report)
    ceiling = report["colour_measure_on_ground_truth"]
    print(f"{report['prompts']} held-out prompts: dominant colour {100 * report['colour_accuracy']:.1f}%, colour shown {100 * report['colour_present']:.1f}%, "
          f"type {100 * report['type_accuracy']:.1f}% (on ground-truth renders of training instances the same measures give "
          f"{100 * ceiling['agreement']:.1f}% and {100 * ceiling['present']:.1f}%); grid {grid}")
    return 0


def cmd_eval_sampling(args) -> int:
    from model.eval.query import sampling
    from model.nerf.device import default_device
    from model.prior.io import load_prior

    _positive("samples", args.samples)
    grid = _beside(args.json, args.grid, ".png")
    paths = _beside(args.json, args.interpolation_grid, "_interpolation.png")
    report = sampling(load_prior(Path(args.run), default_device()), samples=args.samples, temperature=args.temperature, seed=args.seed,
                      grid_png=grid, interpolation_png=paths)
    report["command"] = _command()
    _write_json(args.json, report)
    s, t = report["samples_validity"], report["training_codes_validity"]
    d = report["distance_to_nearest_training_code"]
    print(f"{report['samples']} samples: {d['shape_median']:.2f} / {d['colour_median']:.2f} codebook spacings from the nearest training shape / colour code; "
          f"haze {s['haze_fraction']:.2f} (training codes {t['haze_fraction']:.2f}), watertight {s['watertight_share']:.0%} ({t['watertight_share']:.0%}); grids {grid}, {paths}")
    return 0


def cmd_eval_query_tto(args) -> int:
    from model.eval.query import tto_starts
    from model.optimize.tto import TTOConfig

    _positive("objects", args.objects)
    _positive("steps", args.steps)
    report = tto_starts(_pipeline(args), Path(args.data), objects=args.objects, cfg=TTOConfig(steps=args.steps, patience=0))
    report["command"] = _command()
    _write_json(args.json, report)
    for start, row in report["summary"].items():
        print(f"{start:<8} input view {row['first_input_psnr']:.2f} dB at the start, target reached after {row['time_to_target_s']:.1f} s; "
              f"held-out {row['held_out_psnr']:.2f} dB ({row['held_out_psnr_fg']:.2f} foreground; blank floors {row['held_out_floor_psnr']:.2f} / "
              f"{row['held_out_floor_psnr_fg']:.2f}) after {row['wall_s']:.1f} s")
    return 0
