"""The ``hypnerf`` command line: datasets, per-object fits, the prior, evaluation, benchmarks, demo.

Each command's options are registered only when that command runs (``COMMANDS`` maps it to the
module and function that register it), so ``hypnerf --help`` lists the commands without importing
torch.
"""

from __future__ import annotations

import argparse
import importlib
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


def register_fit(parser: argparse.ArgumentParser) -> None:
    from model.optimize.fit import FitConfig

    defaults = FitConfig()
    parser.add_argument("--data", required=True, help="dataset folder (with index.json)")
    parser.add_argument("--object", required=True, help="object id")
    parser.add_argument("--out", required=True, help="run folder to write")
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--rays", type=int, default=defaults.rays_per_step, help="rays per step")
    parser.add_argument("--grid-resolution", type=int, default=defaults.occupancy.resolution, help="occupancy grid resolution")
    parser.add_argument("--no-masks", action="store_true",
                        help="grow the occupancy grid from the field's density alone, even when the images have alpha (masks only speed it up)")
    parser.add_argument("--mesh-resolution", type=int, default=128)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.set_defaults(func=cmd_fit)


def cmd_fit(args) -> int:
    """Fit one object, evaluate it on its held-out views, write checkpoint, renders, mesh, metrics."""
    from model.eval.field import fit_and_evaluate
    from model.nerf.device import default_device
    from model.nerf.occupancy import OccupancyConfig
    from model.optimize.fit import FitConfig

    for name in ("steps", "rays", "grid_resolution", "mesh_resolution"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be at least 1")
    cfg = FitConfig(steps=args.steps, rays_per_step=args.rays, seed=args.seed, use_masks=not args.no_masks,
                    occupancy=OccupancyConfig(resolution=args.grid_resolution, seed=args.seed))
    fit_and_evaluate(Path(args.data), args.object, Path(args.out), cfg, default_device(), args.mesh_resolution)
    return 0


def register_eval(parser: argparse.ArgumentParser) -> None:
    eval_sub = parser.add_subparsers(dest="eval", required=True)
    comp = eval_sub.add_parser("compression", help="generated NeRFs vs per-object fits (paper Table 2; Table 4 with --ablation no-mrhe)")
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
    dis.add_argument("--grid", help="PNG grid of shape source | colour source | swap per pair (default: beside --json)")
    dis.add_argument("--pairs", type=int, default=10)
    dis.add_argument("--seed", type=int, default=0)
    dis.set_defaults(func=cmd_eval_disentanglement)
    from model.cli.query import register_eval_query

    register_eval_query(eval_sub)
    from model.cli.invert import register_generalization

    register_generalization(eval_sub)


def _fg(value) -> str:
    return f"{value:.2f}" if value is not None else "n/a"


def cmd_eval_compression(args) -> int:
    from model.eval.prior import compression
    from model.nerf.device import default_device

    report = compression(
        Path(args.run), Path(args.data), objects=args.objects, fits=args.fits, fit_steps=args.fit_steps,
        mesh_resolution=args.mesh_resolution, ablation=args.ablation, device=default_device(),
    )
    report["command"] = "hypnerf " + " ".join(sys.argv[1:])
    _write_json(args.json, report)
    h, p = report["hypernet"], report["per_object"]
    print(f"{report['objects']} objects: hypernet {h['psnr']:.2f} dB full / {_fg(h['psnr_fg'])} dB foreground, "
          f"per-object {p['psnr']:.2f} / {_fg(p['psnr_fg'])} dB, blank-image floor {h['floor_psnr']:.2f} / {_fg(h['floor_psnr_fg'])} dB; "
          f"gap {report['psnr_gap_db']:.2f} / {_fg(report['psnr_fg_gap_db'])} dB")
    return 0


def cmd_eval_disentanglement(args) -> int:
    from model.eval.prior import disentanglement

    grid = Path(args.grid) if args.grid else Path(args.json).with_suffix(".png")
    report = disentanglement(Path(args.run), Path(args.data), pairs=args.pairs, seed=args.seed, grid_png=grid)
    report["command"] = "hypnerf " + " ".join(sys.argv[1:])
    _write_json(args.json, report)
    print(f"{report['pairs']} pairs: geometry shared by construction (max density difference {report['geometry_max_density_difference']:.1e}); "
          f"per-pixel colour error to the colour source {report['colour_error_to_color_source_mean']:.1f}, "
          f"to the shape source {report['colour_error_to_shape_source_mean']:.1f} (Delta E); {report['passed']}/{report['pairs']} pass; grid {grid}")
    return 0


def register_swap(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--run", required=True, help="run folder written by `hypnerf train`")
    parser.add_argument("--data", required=True, help="the dataset the prior was trained on (for poses and ground truth)")
    parser.add_argument("--shape", required=True, help="instance id giving the shape code")
    parser.add_argument("--color", required=True, help="instance id giving the colour code")
    parser.add_argument("--out", required=True, help="folder for the renders, mesh.glb and swap.json")
    parser.add_argument("--mesh-resolution", type=int, default=128)
    parser.set_defaults(func=cmd_swap)


def cmd_swap(args) -> int:
    from model.eval.prior import swap

    result = swap(Path(args.run), Path(args.data), args.shape, args.color, Path(args.out), args.mesh_resolution)
    print(json.dumps(result, indent=2))
    return 0


def _write_json(path: str, data: dict) -> None:
    from model.nerf.encodings.kernels import machine_summary

    data.setdefault("machine", machine_summary())
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=2))


def register_bench(parser: argparse.ArgumentParser) -> None:
    bench_sub = parser.add_subparsers(dest="bench", required=True)
    render = bench_sub.add_parser("render", help="renderer speed against error on a fitted object")
    render.add_argument("--fit", required=True, help="run folder written by `hypnerf fit`")
    render.add_argument("--json", required=True, help="where to write the results")
    render.add_argument("--repeats", type=int, default=3)
    render.add_argument("--views", type=int, default=4, help="held-out views rendered per mode")
    render.set_defaults(func=cmd_bench_render)


def cmd_bench_render(args) -> int:
    from model.eval.render_speed import run_render_bench

    report = run_render_bench(Path(args.fit), repeats=args.repeats, views=args.views)
    _write_json(args.json, report)
    for run in report["runs"]:
        print(f"{run['mode']:<24} {run['ms']:9.1f} ms  {run['psnr']:6.2f} dB  fg {_fg(run['psnr_fg']):>6} dB  {run['samples_per_ray']:6.1f} samples/ray")
    return 0


def register_demo(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="runs/demo")
    parser.add_argument("--res", type=int, default=96)
    parser.add_argument("--steps", type=int, default=600)
    parser.set_defaults(func=cmd_demo)


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


# command -> (help, "module:function" registering its options)
COMMANDS: dict[str, tuple[str, str]] = {
    "data": ("build or import multi-view datasets", "model.cli.data:register"),
    "fit": ("fit one object's NeRF (the per-object reference)", "model.cli.main:register_fit"),
    "train": ("train the hypernetwork prior on a category (torchrun -m model.cli train for data parallel)", "model.cli.train:register"),
    "eval": ("evaluate a trained prior", "model.cli.main:register_eval"),
    "invert": ("a NeRF from one or more photos of an unseen object (test-time optimisation of the codes)", "model.cli.invert:register"),
    "train-denoiser": ("train the image-to-image denoiser on renders of the prior", "model.cli.denoise:register"),
    "train-query": ("train the query network (text or image embedding to codes)", "model.cli.query:register_train"),
    "text": ("text-to-NeRF: a NeRF from a text prompt, with renders and a mesh", "model.cli.query:register_text"),
    "sample": ("unconditional samples from a density fitted on the codebook", "model.cli.query:register_sample"),
    "export": ("export a trained run to a verified bundle for the service", "model.cli.bundle:register"),
    "serve": ("serve a bundle over HTTP (FastAPI)", "model.cli.serve:register"),
    "swap": ("a NeRF with one instance's shape and another's colour: renders and mesh", "model.cli.main:register_swap"),
    "bench": ("benchmarks", "model.cli.main:register_bench"),
    "demo": ("end-to-end demo: procedural data, one fit, renders and a mesh", "model.cli.main:register_demo"),
}


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The parser, with the options of the command named in ``argv`` (if any) registered."""
    parser = argparse.ArgumentParser(prog="hypnerf", description=__doc__.split("\n\n")[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (text, target) in COMMANDS.items():
        command = sub.add_parser(name, help=text, description=text)
        if name == chosen:
            module, function = target.split(":")
            getattr(importlib.import_module(module), function)(command)
    return parser


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        _reexec_with_allocator_env()
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as exc:
        log.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
