"""The ``hypnerf data`` command line: ``synth``, ``import-meshes``, ``import-sh3d`` and
``import-transforms`` (argparse).

:func:`register` adds the subcommands to the ``data`` parser. Each subcommand
sets ``func``: called with the parsed arguments, it builds the dataset and returns the exit
status (0 on success, 1 with a message on stderr when the input or environment is at fault).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable
from pathlib import Path

from model.data.build import RenderSettings, SourceObject, build_dataset
from model.data.cameras import DEFAULT_VIEWS
from model.data.imports import UP_AXES, mesh_file_objects, read_captions
from model.data.raycast import DEFAULT_SUPERSAMPLE
from model.data.sh3d import CATEGORIES, Sh3dError, category_rows, sh3d_objects, spread
from model.data.synth import synth_objects

log = logging.getLogger(__name__)


def register(data: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the dataset subcommands to the ``data`` parser and return it."""
    commands = data.add_subparsers(dest="data_command", metavar="COMMAND", required=True)

    render = argparse.ArgumentParser(add_help=False)
    render.add_argument("--out", type=Path, required=True, help="dataset folder (created, or added to)")
    render.add_argument("--views", type=int, default=DEFAULT_VIEWS, help=f"training views per object (default {DEFAULT_VIEWS})")
    render.add_argument("--res", type=int, default=128, help="image width and height in pixels (default 128)")
    render.add_argument(
        "--supersample", type=int, default=DEFAULT_SUPERSAMPLE,
        help=f"rays per pixel side for antialiasing (default {DEFAULT_SUPERSAMPLE})",
    )
    render.add_argument(
        "--variants", type=int, default=1,
        help="objects per mesh: the mesh as it is plus N-1 colour/material variants (ids <id>-v1, ...; default 1)",
    )
    render.add_argument(
        "--augment", type=int, default=0,
        help="deformed copies of each train-split mesh as new shapes (ids <id>-augK; scaled, stretched, mirrored; default 0)",
    )

    synth = commands.add_parser("synth", parents=[render], help="procedural chairs", description="Render procedural chairs.")
    synth.add_argument("--objects", type=int, default=16, help="number of chairs (default 16)")
    synth.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    synth.set_defaults(func=_run_synth)

    meshes = commands.add_parser(
        "import-meshes", parents=[render], help="your OBJ/GLB/PLY files",
        description="Normalise and render mesh files (OBJ+MTL, GLB/glTF, PLY) into a dataset.",
    )
    meshes.add_argument("--category", required=True, help="category of every file, e.g. chair")
    meshes.add_argument(
        "--captions", type=Path,
        help="captions by file stem: JSON {\"stem\": \"caption\"} or TSV 'stem<TAB>caption' lines",
    )
    meshes.add_argument("--up", choices=UP_AXES, default="y", help="up axis of the files (default y, as in glTF)")
    meshes.add_argument("paths", nargs="+", type=Path, metavar="PATH", help="mesh files")
    meshes.set_defaults(func=_run_import_meshes)

    sh3d = commands.add_parser(
        "import-sh3d", parents=[render], help="furniture from Debian's sweethome3d-furniture",
        description="Render chairs, tables or sofas of Debian's sweethome3d-furniture package "
        "(downloaded with apt-get into $HYPNERF_CACHE/sweethome3d on first use).",
    )
    sh3d.add_argument("--category", choices=CATEGORIES, required=True)
    sh3d.add_argument("--limit", type=int, help="render only N models, spread evenly over the category list")
    sh3d.set_defaults(func=_run_import_sh3d)

    transforms = commands.add_parser(
        "import-transforms", help="an existing multi-view scene (NeRF-synthetic or nerfstudio transforms.json)",
        description="Import a posed multi-view scene: the NeRF-synthetic layout (transforms_train/val/test.json) or "
        "nerfstudio's transforms.json, keeping its pinhole intrinsics and scene box.",
    )
    transforms.add_argument("source", type=Path, metavar="SRC", help="folder holding transforms_train.json or transforms.json")
    transforms.add_argument("--out", type=Path, required=True, help="dataset folder to write (one object)")
    transforms.add_argument("--id", help="object id (default: the source folder's name)")
    transforms.add_argument("--category", default="object", help="category written to index.json (default object)")
    transforms.add_argument("--downscale", type=int, default=1, help="shrink images by this integer factor (default 1)")
    transforms.add_argument("--aabb", type=float, nargs=6, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                            help="scene box (default: the file's aabb, else the convention's, else derived from the cameras)")
    transforms.add_argument("--test-every", type=int, default=8,
                            help="for files without splits, every Nth frame is held out for testing (default 8)")
    transforms.set_defaults(func=_run_import_transforms)
    return data


def _build(args, source: Callable[[], tuple[Iterable[SourceObject], int]]) -> int:
    """Render what ``source()`` lists into ``args.out``; expected failures become a message and status 1."""
    try:
        settings = RenderSettings(
            views=args.views, resolution=args.res, supersample=args.supersample, variants=args.variants, augment=args.augment
        )
        objects, total = source()
        start = time.perf_counter()
        entries = build_dataset(args.out, objects, settings, total=total)
    except (ValueError, Sh3dError) as error:
        # DatasetError is a ValueError: every expected failure lands here with its own advice.
        print(f"hypnerf data: error: {error}", file=sys.stderr)
        return 1
    splits = Counter(entry.split for entry in entries)
    log.info(
        "dataset %s: %d objects (train %d, val %d, test %d) in %.1f s",
        args.out, len(entries), splits["train"], splits["val"], splits["test"], time.perf_counter() - start,
    )
    return 0


def _run_synth(args) -> int:
    return _build(args, lambda: (synth_objects(args.objects, args.seed), args.objects))


def _run_import_meshes(args) -> int:
    def source():
        captions = read_captions(args.captions) if args.captions else {}
        return mesh_file_objects(args.paths, args.category, captions, args.up), len(args.paths)

    return _build(args, source)


def _run_import_transforms(args) -> int:
    from model.data.transforms import import_transforms

    try:
        report = import_transforms(
            args.source, args.out, object_id=args.id, category=args.category, downscale=args.downscale,
            aabb=[args.aabb[:3], args.aabb[3:]] if args.aabb else None, test_every=args.test_every,
        )
    except ValueError as error:
        print(f"hypnerf data: error: {error}", file=sys.stderr)
        return 1
    log.info(
        "imported %s (%s layout): %d frames (%s) at %dx%d, scene box %s (%s) -> %s",
        report["id"], report["layout"], report["frames"], report["splits"], report["width"], report["height"],
        report["aabb"], report["aabb_source"], args.out,
    )
    return 0


def _run_import_sh3d(args) -> int:
    def source():
        total = len(spread(category_rows(args.category), args.limit))
        return sh3d_objects(args.category, args.limit), total

    return _build(args, source)
