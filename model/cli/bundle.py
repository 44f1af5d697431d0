"""``hypnerf export``: a trained prior run to a verified bundle, and ``--verify`` of an existing one."""

from __future__ import annotations

import argparse
import collections
import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)


def register(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--run", help="prior run folder written by `hypnerf train` (prior.json + hypernet.safetensors)")
    parser.add_argument("--out", help="bundle folder to write (an earlier bundle there is replaced)")
    parser.add_argument("--data", help="the dataset the prior was trained on, for attribution (default: the one prior.json records)")
    parser.add_argument("--query", help="query-network run folder to include")
    parser.add_argument("--denoiser", help="denoiser folder (denoiser.safetensors + denoiser.json) to include")
    parser.add_argument("--verify", metavar="BUNDLE", help="verify an existing bundle and print its summary (no export)")
    parser.set_defaults(func=cmd_export)


def summary(path: Path) -> list[str]:
    """Load a bundle with full verification and describe it: files, components, instances, licences,
    load time, and the ONNX-vs-torch differences (first instance's NeRF and render; query codes)."""
    from model.bundle import load_bundle
    from model.bundle.parity import parity, query_parity

    start = time.perf_counter()
    bundle = load_bundle(path)
    seconds = time.perf_counter() - start
    files = bundle.manifest["files"]
    total = sum(record["bytes"] for record in files.values()) + (path / "manifest.json").stat().st_size
    licences = collections.Counter(record["licence"] for record in bundle.manifest["attribution"])
    shapes = len({inst["shape_id"] for inst in bundle.instances})
    check = parity(bundle, bundle.shape_codes[0], bundle.color_codes[0])
    camera = f"{bundle.camera.width}x{bundle.camera.height}"
    lines = [
        f"bundle {path}: format {bundle.manifest['format']}, digest {bundle.digest}, created {bundle.manifest['created']}",
        f"verified {len(files)} files ({total / 1e6:.1f} MB with the manifest) and loaded in {seconds:.2f} s",
        *(f"  {name:<24} {record['bytes']:>12,} bytes  sha256 {record['sha256'][:16]}" for name, record in sorted(files.items())),
        f"components: {', '.join(bundle.manifest['components'])}",
        f"{len(bundle.instances)} instances of {shapes} shapes; codes {bundle.shape_codes.shape[1]} + {bundle.color_codes.shape[1]}; "
        + f"camera {camera}; scene box {bundle.scene.to_aabb()}",
        f"ONNX Runtime vs torch on {bundle.instances[0]['id']}: parameters max |diff| {check['params_max_abs_diff']:.1e}, "
        + f"{camera} render max |diff| {check['image_max_abs_diff']:.1e} (object on {100 * check['coverage']:.0f}% of the pixels)",
    ]
    if bundle.query is not None:
        reads = ", ".join(f"{slot.name} ({modality})" for slot in bundle.query.slots for modality in slot.modalities)
        rows, width = bundle.query.bank.shape
        lines.append(f"query network: reads {reads}; retrieval bank {rows} x {width}; ONNX Runtime vs torch codes max |diff| {query_parity(bundle):.1e}")
    lines.append("training data licences:")
    lines += [f"  {count:>4} x {licence}" for licence, count in licences.most_common()]
    return lines


def cmd_export(args) -> int:
    if args.verify:
        if args.run or args.out:
            raise ValueError("--verify checks an existing bundle; give either --verify BUNDLE or --run RUN --out BUNDLE")
        print("\n".join(summary(Path(args.verify))))
        return 0
    if not (args.run and args.out):
        raise ValueError("export needs --run RUN and --out BUNDLE (or --verify BUNDLE to check one)")
    from model.bundle import export_bundle

    out = export_bundle(
        Path(args.run), Path(args.out), data=Path(args.data) if args.data else None,
        query=Path(args.query) if args.query else None, denoiser=Path(args.denoiser) if args.denoiser else None,
    )
    print("\n".join(summary(out)))
    return 0
