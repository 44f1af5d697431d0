"""``hypnerf invert`` (a NeRF from photos of an unseen object) and ``hypnerf eval generalization``.

The pose file follows transforms.json: ``camera_angle_x`` (or ``fl_x``/``fl_y``/``cx``/``cy``) at
the top or per frame, and ``frames`` with a 4x4 camera-to-world ``transform_matrix`` each, in the
order of the ``--image`` arguments (or with a ``file_path`` each when no ``--image`` is given).
Without a pose file one image is inverted with its pose searched for (azimuth, elevation) and
refined with the codes, seen through ``--fov`` or the prior's category camera; the pose found is
written as ``pose.json`` in the same format.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("hypnerf")


def register(parser: argparse.ArgumentParser) -> None:
    from model.optimize.tto import TTOConfig

    defaults = TTOConfig()
    parser.add_argument("--run", required=True, help="run folder written by `hypnerf train`")
    parser.add_argument("--image", action="append", default=[], help="an input photo (PNG/JPEG; RGBA keeps its mask); repeat for more views")
    parser.add_argument("--mask", action="append", default=[], help="a mask per --image (white = object), for photos without alpha")
    parser.add_argument("--pose", help="transforms.json-style file with the camera of each image; without it the pose of a single image is searched for")
    parser.add_argument("--fov", type=float, help="horizontal field of view in degrees of an image without a pose file (default: the prior's camera)")
    parser.add_argument("--refine-pose", action="store_true", help="optimise each given pose with the codes (for roughly known poses)")
    parser.add_argument("--mirror", action="store_true", help="add each view mirrored left-right, a virtual second view of a symmetric object")
    parser.add_argument("--out", required=True, help="folder for codes, the NeRF, renders, turntable and mesh")
    parser.add_argument("--steps", type=int, default=defaults.steps, help="code optimisation steps")
    parser.add_argument("--finetune-steps", type=int, default=defaults.finetune_steps, help="steps optimising the NeRF's own parameters afterwards")
    parser.add_argument("--rays", type=int, default=defaults.rays_per_step)
    parser.add_argument("--init", choices=["nearest", "mean", "query"], default=defaults.init,
                        help="starting codes: the nearest training instance, the mean code, or the query network's guess from the first image (needs --query)")
    parser.add_argument("--query", help="query network folder from `hypnerf train-query` (for --init query)")
    parser.add_argument("--denoise", action="store_true", help="then denoise-and-finetune: render fixed views, denoise them, finetune the NeRF on them")
    parser.add_argument("--denoiser", help="denoiser folder from `hypnerf train-denoiser` (for --denoise)")
    parser.add_argument("--denoise-steps", type=int, help="finetune steps on the denoised views per round (default 300)")
    parser.add_argument("--denoise-rounds", type=int, help="rounds of render, denoise and finetune, each on the NeRF the round before finetuned (default 2)")
    parser.add_argument("--denoise-mirror", action=argparse.BooleanOptionalAction, default=None,
                        help="finetune on the input photos' mirror images too (a left-right symmetric object; default on, --no-denoise-mirror for one that is not)")
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--mesh-resolution", type=int, default=128)
    parser.set_defaults(func=cmd_invert)


def read_inputs(images: list[str], masks: list[str], pose_file: Path | None, camera=None):
    """Images ``[V, H, W, 4]`` in [0, 1], poses ``[V, 4, 4]`` (None without a pose file) and one
    camera per image from the command's files; without a pose file ``camera(width, height)`` gives
    the camera of the single image."""
    import numpy as np
    import torch
    from PIL import Image, UnidentifiedImageError

    from model.data.dataset import frame_intrinsics

    if pose_file is None:
        if len(images) != 1:
            raise ValueError(f"without --pose give exactly one --image (its pose is searched for); got {len(images)}")
        data, frames = {}, [None]
    else:
        try:
            data = json.loads(pose_file.read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise ValueError(f"cannot read the pose file {pose_file}: {error}") from None
        frames = data.get("frames") if isinstance(data, dict) else None
        if not isinstance(frames, list) or not frames:
            raise ValueError(f"{pose_file} needs a non-empty 'frames' list, each with a 4x4 'transform_matrix'")
    paths = [Path(p) for p in images] or [pose_file.parent / f.get("file_path", "") for f in frames]
    if len(paths) != len(frames):
        raise ValueError(f"{len(paths)} images but {len(frames)} frames in {pose_file}; give one frame per image, in order")
    if masks and len(masks) != len(paths):
        raise ValueError(f"{len(masks)} masks for {len(paths)} images; give a mask for every image or none")
    rgba, poses, cameras = [], [], []
    for number, (path, frame) in enumerate(zip(paths, frames)):
        try:
            with Image.open(path) as image:
                array = np.asarray(image.convert("RGBA"), dtype=np.float32) / 255.0
            if masks:
                with Image.open(masks[number]) as mask:
                    mask = mask.convert("L")
                    if mask.size != (array.shape[1], array.shape[0]):
                        raise ValueError(f"mask {masks[number]} is {mask.size[0]}x{mask.size[1]}, its image {array.shape[1]}x{array.shape[0]}")
                    array[..., 3] = np.asarray(mask, dtype=np.float32) / 255.0
        except (OSError, UnidentifiedImageError) as error:
            raise ValueError(f"cannot read {path} as an image: {error}") from None
        rgba.append(array)
        if pose_file is None:
            cameras.append(camera(array.shape[1], array.shape[0]))
            continue
        matrix = np.asarray(frame.get("transform_matrix"), dtype=np.float32) if isinstance(frame, dict) else None
        if matrix is None or matrix.shape != (4, 4):
            raise ValueError(f"{pose_file} frame {number}: 'transform_matrix' must be a 4x4 camera-to-world matrix")
        poses.append(matrix)
        cameras.append(frame_intrinsics(data, frame, array.shape[1], array.shape[0], f"{pose_file} frame {number}"))
    if len({a.shape for a in rgba}) != 1:
        raise ValueError("all input images must have the same size")
    return torch.from_numpy(np.stack(rgba)), torch.from_numpy(np.stack(poses)) if poses else None, cameras


def search_camera(prior, fov: float | None):
    """``(width, height) -> Intrinsics`` for an image without a pose file: ``fov`` degrees across,
    or the prior's category camera's field of view."""
    import math

    from model.nerf.rays import Intrinsics

    if fov is not None and not 1.0 <= fov <= 170.0:
        raise ValueError(f"--fov is a horizontal field of view in degrees between 1 and 170, got {fov}")
    cam = prior.meta["camera"]
    angle = math.radians(fov) if fov is not None else 2.0 * math.atan(0.5 * cam["width"] / cam["fx"])
    return lambda width, height: Intrinsics.from_fov(width, height, angle)


def pose_record(c2w, cameras) -> dict:
    """transforms.json-style record of the poses TTO ended with (refined or found)."""
    return {"frames": [{"transform_matrix": pose.tolist(), "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy}
                       for pose, cam in zip(c2w.cpu(), cameras, strict=True)]}


def cmd_invert(args) -> int:
    """Optimise codes for the input views (optionally denoise and finetune), then write the NeRF,
    renders, turntable, mesh and the poses used."""
    from tqdm import tqdm

    from model.nerf import config
    from model.nerf.device import default_device
    from model.optimize.tto import TTOConfig, invert
    from model.prior.io import load_prior
    from model.prior.outputs import write_outputs

    if args.init == "query" and not args.query:
        raise ValueError("--init query starts from the query network's guess; give its folder with --query (from `hypnerf train-query`)")
    if args.denoise and not args.denoiser:
        raise ValueError("--denoise needs a denoiser: give its folder with --denoiser (from `hypnerf train-denoiser`)")
    denoise_options = [flag for flag, value in (("--denoise-steps", args.denoise_steps), ("--denoise-rounds", args.denoise_rounds),
                                                ("--denoise-mirror", args.denoise_mirror)) if value is not None]
    if denoise_options and not args.denoise:
        raise ValueError(f"{', '.join(denoise_options)}: denoise-and-finetune settings, used only with --denoise; add --denoise (and --denoiser)")
    if args.pose and args.fov is not None:
        raise ValueError("--fov is for an image without a pose file; the pose file gives the camera (camera_angle_x or fl_x)")
    prior = load_prior(Path(args.run), default_device())
    pose_file = Path(args.pose) if args.pose else None
    images, c2w, cameras = read_inputs(args.image, args.mask, pose_file, search_camera(prior, args.fov) if pose_file is None else None)
    cfg = TTOConfig(steps=args.steps, finetune_steps=args.finetune_steps, rays_per_step=args.rays,
                    init="nearest" if args.init == "query" else args.init, seed=args.seed, refine_pose=args.refine_pose, mirror=args.mirror)
    init = None
    if args.init == "query":
        from model.prior.query import QueryPipeline, load_query

        pipeline = QueryPipeline(prior, load_query(Path(args.query), prior.device), prior.device)
        shape, color = pipeline.codes(pipeline.embed(image=images[0]), snap=False)
        init = (shape[0], color[0])
    denoise = None
    if args.denoise:
        from dataclasses import replace

        from model.denoise.finetune import DenoiseConfig, denoise_and_finetune_prior

        settings = DenoiseConfig()
        if args.denoise_steps is not None:
            if args.denoise_steps < 1:
                raise ValueError(f"--denoise-steps must be at least 1, got {args.denoise_steps}")
            settings = replace(settings, finetune=replace(settings.finetune, steps=args.denoise_steps))
        if args.denoise_rounds is not None:
            if args.denoise_rounds < 1:
                raise ValueError(f"--denoise-rounds must be at least 1, got {args.denoise_rounds}")
            settings = replace(settings, rounds=args.denoise_rounds)
        if args.denoise_mirror is not None:
            settings = replace(settings, mirror_inputs=args.denoise_mirror)
        denoise = denoise_and_finetune_prior(Path(args.denoiser), settings)  # loaded before the long part: a bad folder fails now
    log.info("optimising codes for %d view(s) of %dx%d%s", len(images), images.shape[2], images.shape[1],
             ", searching for the pose" if c2w is None else "")
    bar = tqdm(total=cfg.steps + cfg.finetune_steps, desc="invert", unit="step")

    def progress(entry: dict) -> None:
        bar.update(entry["step"] + 1 - bar.n)
        bar.set_postfix(phase=entry["phase"], psnr=f"{entry['psnr']:.2f}")

    result = invert(prior.net, prior.scene, images, c2w, cameras, cfg, init=init, progress=progress)
    bar.close()
    params, grid = result.params, result.grid
    if denoise is not None:
        log.info("denoise and finetune (%d round(s)): rendering fixed views, denoising them, finetuning the NeRF on them", settings.rounds)
        finetune_bar = tqdm(total=settings.total_steps, desc="denoise and finetune", unit="step")

        def finetune_progress(entry: dict) -> None:
            finetune_bar.update(entry["step"] + 1 - finetune_bar.n)
            finetune_bar.set_postfix(psnr=f"{entry['psnr']:.2f}")

        params, grid = denoise(prior, {k: v.to(prior.device) for k, v in params.items()}, (images, result.c2w, cameras), finetune_progress)
        finetune_bar.close()
    out = Path(args.out)
    codes = {"shape": result.shape_code.tolist(), "color": result.color_code.tolist(), "init": result.init}
    extra = {"tto": config.to_dict(cfg), "codes": codes, "prior": str(args.run), "wall_s": result.wall_s,
             "finetuned": cfg.finetune_steps > 0, "denoised": denoise is not None, "denoiser": args.denoiser if denoise is not None else None,
             "denoise": config.to_dict(settings) if denoise is not None else None,
             "pose": "searched" if c2w is None else ("refined" if cfg.refine_pose else "given")}
    log.info("writing renders, turntable and mesh into %s", out)
    paths = write_outputs(out, params, prior.net.cfg.field, grid, prior.scene, cameras[0], extra=extra, mesh_resolution=args.mesh_resolution)
    (out / "codes.json").write_text(json.dumps(codes, indent=2))
    (out / "history.json").write_text(json.dumps(result.history, indent=2))
    (out / "pose.json").write_text(json.dumps(pose_record(result.c2w, cameras), indent=2))
    final = result.history[-1]
    print(f"inverted in {result.wall_s:.1f} s from {result.init} (pose {extra['pose']}): training-view PSNR {final['psnr']:.2f} dB"
          + ("; denoised and finetuned" if denoise is not None else "")
          + f"; NeRF {paths['nerf']}, renders {paths['renders']}, turntable {paths['turntable']}, mesh {paths['mesh']}, poses {out / 'pose.json'}")
    return 0


def register_generalization(eval_sub) -> None:
    from model.eval.generalization import ROWS

    gen = eval_sub.add_parser("generalization", help="NeRFs of unseen test objects from one view (paper Table 1)")
    gen.add_argument("--run", required=True, help="run folder written by `hypnerf train`")
    gen.add_argument("--data", required=True, help="the dataset the prior was trained on (its test split is used)")
    gen.add_argument("--json", required=True, help="where to write the report (a PNG of renders goes beside it)")
    gen.add_argument("--objects", type=int, default=11)
    gen.add_argument("--views", type=int, default=1, help="input views per object")
    gen.add_argument("--steps", type=int, help="TTO steps (default: the TTO default)")
    gen.add_argument("--finetune-steps", type=int, default=0)
    gen.add_argument("--fit-steps", type=int, default=500, help="steps of the single-view fit baseline")
    gen.add_argument("--denoiser", help="a denoiser folder from `hypnerf train-denoiser` (adds the tto_denoise row)")
    gen.add_argument("--denoise-rounds", type=int, help="rounds of denoise-and-finetune in the tto_denoise row (default 2)")
    gen.add_argument("--denoise-mirror", action=argparse.BooleanOptionalAction, default=None,
                     help="the tto_denoise row's finetune also on the input photo's mirror image (default on)")
    gen.add_argument("--rows", help=f"comma-separated rows to compute (default all of {','.join(ROWS)})")
    gen.set_defaults(func=cmd_eval_generalization)


def cmd_eval_generalization(args) -> int:
    from model.cli.main import _write_json
    from model.denoise.finetune import DenoiseConfig
    from model.eval.generalization import ROWS, GeneralizationConfig, generalization
    from model.optimize.tto import TTOConfig

    tto = TTOConfig(finetune_steps=args.finetune_steps, **({"steps": args.steps} if args.steps else {}))
    rows = tuple(r.strip() for r in args.rows.split(",") if r.strip()) if args.rows else ROWS
    unknown = sorted(set(rows) - set(ROWS))
    if unknown or not rows:
        print(f"hypnerf eval generalization: error: unknown rows {unknown or rows}; choose from {', '.join(ROWS)}", file=sys.stderr)
        return 2
    if args.denoise_rounds is not None and args.denoise_rounds < 1:
        print(f"hypnerf eval generalization: error: --denoise-rounds must be at least 1, got {args.denoise_rounds}", file=sys.stderr)
        return 2
    denoise = DenoiseConfig(**({"rounds": args.denoise_rounds} if args.denoise_rounds else {}),
                            **({"mirror_inputs": args.denoise_mirror} if args.denoise_mirror is not None else {}))
    cfg = GeneralizationConfig(objects=args.objects, input_views=args.views, tto=tto, denoise=denoise, fit_steps=args.fit_steps, rows=rows)
    out = Path(args.json)
    report = generalization(Path(args.run), Path(args.data), cfg, denoiser=Path(args.denoiser) if args.denoiser else None, out=out)
    report["command"] = "hypnerf " + " ".join(sys.argv[1:])
    _write_json(str(out), report)
    for row, q in report["rows"].items():
        print(f"{row:16s} {q['psnr']:6.2f} dB full  {q['psnr_fg']:6.2f} dB fg  SSIM {q['ssim']:.3f}  FID {q['fid']:.3f}")
    print(f"blank-image floor {report['floor_psnr']:.2f} / {report['floor_psnr_fg']:.2f} dB; {report['objects']} objects; renders {out.with_suffix('.png')}")
    return 0
