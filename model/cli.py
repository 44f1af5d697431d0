"""The ``hypnerf`` command line: datasets, per-object fits, renders, meshes, benchmarks, demo."""

from __future__ import annotations

import argparse
import json
import logging
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
    from model.device import default_device
    from model.evaluate import fit_and_evaluate

    fit_and_evaluate(Path(args.data), args.object, Path(args.out), _fit_config(args), default_device(), args.mesh_resolution)
    return 0


def cmd_eval_compression(args) -> int:
    from model.device import default_device
    from model.prior_eval import compression

    report = compression(
        Path(args.run), Path(args.data), objects=args.objects, fits=args.fits, fit_steps=args.fit_steps,
        mesh_resolution=args.mesh_resolution, ablation=args.ablation, device=default_device(),
    )
    report["command"] = "hypnerf " + " ".join(sys.argv[1:])
    _write_json(args.json, report)
    h, p = report["hypernet"], report["per_object"]
    print(f"{report['objects']} objects: hypernet {h['psnr']:.2f} dB / SSIM {h['ssim']:.4f} / Chamfer {h['chamfer']:.4f}; "
          f"per-object {p['psnr']:.2f} dB / SSIM {p['ssim']:.4f} / Chamfer {p['chamfer']:.4f}; gap {report['psnr_gap_db']:.2f} dB")
    return 0


def cmd_eval_disentanglement(args) -> int:
    from model.prior_eval import disentanglement

    report = disentanglement(Path(args.run), Path(args.data), pairs=args.pairs, mesh_resolution=args.mesh_resolution, seed=args.seed)
    report["command"] = "hypnerf " + " ".join(sys.argv[1:])
    _write_json(args.json, report)
    print(f"{report['pairs']} pairs: Chamfer ratio mean {report['chamfer_ratio_mean']:.2f} (max {report['chamfer_ratio_max']:.2f}); "
          f"colour distance to colour source {report['colour_distance_to_color_source_mean']:.1f}, "
          f"to shape source {report['colour_distance_to_shape_source_mean']:.1f} (Delta E)")
    return 0


def cmd_swap(args) -> int:
    from model.prior_eval import swap

    result = swap(Path(args.run), Path(args.data), args.shape, args.color, Path(args.out), args.mesh_resolution)
    print(json.dumps(result, indent=2))
    return 0


def _write_json(path: str, data: dict) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=2))


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

    from model.train import add_arguments as add_train_arguments
    from model.train import run_from_args as run_train

    train = sub.add_parser(
        "train", help="train the hypernetwork prior on a category",
        description="Train the hypernetwork prior on the train split of a dataset. For data-parallel "
        "training run `torchrun --nproc_per_node=N -m model.train` with the same options.",
    )
    add_train_arguments(train)
    train.set_defaults(func=run_train)

    evaluate = sub.add_parser("eval", help="evaluate a trained prior")
    eval_sub = evaluate.add_subparsers(dest="eval", required=True)
    comp = eval_sub.add_parser(
        "compression", help="generated NeRFs vs per-object fits (paper Table 2; Table 4 with --ablation no-mrhe)",
    )
    comp.add_argument("--run", required=True, help="run folder written by `hypnerf train`")
    comp.add_argument("--data", required=True, help="the dataset the prior was trained on")
    comp.add_argument("--json", required=True, help="where to write the report")
    comp.add_argument("--objects", type=int, default=10, help="training instances compared (default 10)")
    comp.add_argument("--fits", help="folder of per-object fits to reuse or fill (default RUN/per-object-fits)")
    comp.add_argument("--fit-steps", type=int, help="steps of each per-object fit (default: the fit default)")
    comp.add_argument("--mesh-resolution", type=int, default=128)
    comp.add_argument("--ablation", choices=["no-mrhe"], help="the prior emits a positional-encoding NeRF")
    comp.set_defaults(func=cmd_eval_compression)
    dis = eval_sub.add_parser("disentanglement", help="swap shape and colour codes of instance pairs (paper section 4.5)")
    dis.add_argument("--run", required=True)
    dis.add_argument("--data", required=True)
    dis.add_argument("--json", required=True)
    dis.add_argument("--pairs", type=int, default=10)
    dis.add_argument("--mesh-resolution", type=int, default=128)
    dis.add_argument("--seed", type=int, default=0)
    dis.set_defaults(func=cmd_eval_disentanglement)

    swap = sub.add_parser("swap", help="a NeRF with one instance's shape and another's colour: renders and mesh")
    swap.add_argument("--run", required=True, help="run folder written by `hypnerf train`")
    swap.add_argument("--data", required=True, help="the dataset the prior was trained on (for poses and ground truth)")
    swap.add_argument("--shape", required=True, help="instance id giving the shape code")
    swap.add_argument("--color", required=True, help="instance id giving the colour code")
    swap.add_argument("--out", required=True, help="folder for the renders, mesh.glb and swap.json")
    swap.add_argument("--mesh-resolution", type=int, default=128)
    swap.set_defaults(func=cmd_swap)

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
