"""The ``hypnerf`` command line: datasets, per-object fits, renders, meshes, benchmarks, demo."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from pathlib import Path

# glibc returns freed memory to the OS eagerly and re-faults it on the next allocation, which costs
# 2-4x in torch code on small machines; these settings keep it mapped. They are read when the
# process starts, so the console script re-executes itself once with them set.
_ALLOCATOR_ENV = {
    "MALLOC_MMAP_THRESHOLD_": "34359738368",
    "MALLOC_TRIM_THRESHOLD_": "34359738368",
    "THP_MEM_ALLOC_ENABLE": "1",
}

log = logging.getLogger("hypnerf")


def _reexec_with_allocator_env() -> None:
    if all(k in os.environ for k in _ALLOCATOR_ENV):
        return
    env = {**os.environ, **_ALLOCATOR_ENV}
    os.execve(sys.executable, [sys.executable, "-m", "model.cli", *sys.argv[1:]], env)


def _fit_config(args):
    from model.fit import FitConfig

    cfg = FitConfig(steps=args.steps, rays_per_step=args.rays, seed=args.seed)
    if args.grid_resolution:
        cfg.grid_resolution = args.grid_resolution
    return cfg


def cmd_fit(args) -> int:
    """Fit one object, evaluate it on its held-out views, write checkpoint, renders, mesh, metrics."""
    from model.data.dataset import load_views
    from model.device import default_device
    from model.evaluate import evaluate_field
    from model.fit import fit_object, save_fit
    from model.images import save_png
    from model.mesh import export_mesh
    from model.renderer import RenderConfig

    device = default_device()
    root, out = Path(args.data), Path(args.out)
    train = load_views(root / args.object, split="train")
    test = load_views(root / args.object, split="test")
    cfg = _fit_config(args)
    log.info("fitting %s (%d training views, %dx%d) on %s", args.object, len(train.c2w), train.width, train.height, device)
    result = fit_object(train, cfg, device=device)
    save_fit(out, result, cfg, {"data": str(root.resolve()), "object": args.object})
    log.info("evaluating on %d held-out views", len(test.c2w))
    metrics, renders, mesh = evaluate_field(result.params, cfg.field, result.grid, test, RenderConfig(), mesh_resolution=args.mesh_resolution)
    if not math.isfinite(metrics.get("chamfer", 0.0)):
        log.warning("the fitted field has no surface above the mesh threshold; chamfer is reported as null")
        metrics["chamfer"] = None
    metrics.update({"wall_s": result.wall_s, "object": args.object, "steps": cfg.steps, "occupied_fraction": result.grid.fraction})
    (out / "renders").mkdir(exist_ok=True)
    for i, image in enumerate(renders):
        save_png(out / "renders" / f"test_{i:03d}.png", image)
    export_mesh(mesh, out / "mesh.glb")
    (out / "history.json").write_text(json.dumps(result.history, indent=2))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    log.info(
        "%s: PSNR %.2f dB, SSIM %.4f, Chamfer %s, fit %.1f s -> %s",
        args.object,
        metrics["psnr"],
        metrics["ssim"],
        f"{metrics['chamfer']:.4f}" if metrics.get("chamfer") is not None else "n/a",
        result.wall_s,
        out,
    )
    return 0


def cmd_bench_render(args) -> int:
    from model.render_bench import run_render_bench

    report = run_render_bench(Path(args.fit), repeats=args.repeats, views=args.views)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(report, indent=2))
    for run in report["runs"]:
        print(f"{run['mode']:<28} {run['ms']:9.1f} ms  {run['psnr']:6.2f} dB  {run['samples_per_ray']:6.1f} samples/ray")
    return 0


def cmd_demo(args) -> int:
    """End-to-end demo of what exists: a procedural dataset, one per-object fit, renders and a mesh."""
    out = Path(args.out)
    data = out / "data"
    if not (data / "index.json").is_file():
        code = main(["data", "synth", "--out", str(data), "--objects", "3", "--views", "91", "--res", str(args.res), "--seed", "0"])
        if code:
            return code
    from model.data.dataset import load_index

    first = load_index(data)[0].id
    code = main(["fit", "--data", str(data), "--object", first, "--out", str(out / "fit"), "--steps", str(args.steps)])
    if code:
        return code
    print(f"demo finished: renders in {out / 'fit' / 'renders'}, mesh {out / 'fit' / 'mesh.glb'}, metrics {out / 'fit' / 'metrics.json'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from model.data.commands import register as register_data

    parser = argparse.ArgumentParser(prog="hypnerf", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    register_data(sub)

    fit = sub.add_parser("fit", help="fit one object's NeRF (the per-object reference)")
    fit.add_argument("--data", required=True, help="dataset folder (with index.json)")
    fit.add_argument("--object", required=True, help="object id")
    fit.add_argument("--out", required=True, help="run folder to write")
    fit.add_argument("--steps", type=int, default=1500)
    fit.add_argument("--rays", type=int, default=4096, help="rays per step")
    fit.add_argument("--grid-resolution", type=int, default=0, help="occupancy grid resolution (default 64)")
    fit.add_argument("--mesh-resolution", type=int, default=128)
    fit.add_argument("--seed", type=int, default=0)
    fit.set_defaults(func=cmd_fit)

    bench = sub.add_parser("bench", help="benchmarks")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    render = bench_sub.add_parser("render", help="renderer speed against error on a fitted object")
    render.add_argument("--fit", required=True, help="run folder written by `hypnerf fit`")
    render.add_argument("--json", required=True, help="where to write the results")
    render.add_argument("--repeats", type=int, default=3)
    render.add_argument("--views", type=int, default=4, help="held-out views rendered per mode")
    render.set_defaults(func=cmd_bench_render)

    demo = sub.add_parser("demo", help="end-to-end demo: procedural data, one fit, renders and a mesh")
    demo.add_argument("--out", default="runs/demo")
    demo.add_argument("--res", type=int, default=96)
    demo.add_argument("--steps", type=int, default=600)
    demo.set_defaults(func=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        _reexec_with_allocator_env()
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as exc:
        log.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
