"""Mesh files a user brings (OBJ+MTL, GLB/glTF, PLY, ...) as dataset objects.

- Ids are the file stems made folder-safe (``Office Chair.glb`` -> ``office-chair``), with
  ``-2``, ``-3``... appended when stems repeat.
- Axes: sources are Y-up by default (glTF by specification, most OBJ exporters) and are turned
  upright into the Z-up world; pass ``up="z"`` for Z-up files (CAD exports, many scans).
- Captions: a captions file maps file stem to caption, either JSON (``{"stem": "caption"}``)
  or TSV (``stem<TAB>caption`` per line, ``#`` comments), chosen by the ``.json`` extension.
  Files it does not cover get "a <main colour> <name>", where the name is the stem's words when
  they mention the category and the category otherwise (``a black office chair``,
  ``a brown chair``).
- ``index.json`` records ``source: "file"``, the file name, the name, and the texture status
  (``tex_ok``: textures loaded, ``color_only``: colours only, ``tex_missing``: a texture file
  named by the model was not found and its material colour was used instead).
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import numpy as np

from model.data.build import SourceObject, slug
from model.data.colours import default_caption
from model.data.meshes import RenderMesh, load_mesh_file, y_up_to_z_up

log = logging.getLogger(__name__)

UP_AXES = ("y", "z")


def read_captions(path: Path) -> dict[str, str]:
    """Stem-to-caption mapping from a JSON object or a two-column TSV file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise ValueError(f"cannot read the captions file {path}: {error}") from error
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"{path} is not valid JSON ({error}); write {{\"stem\": \"caption\", ...}}") from error
        if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
            raise ValueError(f"{path} must be a JSON object mapping file stems to caption strings")
        return {str(k): v.strip() for k, v in data.items()}
    captions = {}
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        stem, tab, caption = line.partition("\t")
        if not tab or not caption.strip():
            raise ValueError(f"{path}:{number}: expected 'stem<TAB>caption', got {line!r}")
        captions[stem.strip()] = caption.strip()
    return captions


def texture_status(mesh: RenderMesh, missing: list[str]) -> str:
    """``tex_missing``, ``tex_ok`` or ``color_only`` (the vocabulary of the Sweet Home 3D category list)."""
    if missing:
        return "tex_missing"
    return "tex_ok" if any(m.texture is not None for m in mesh.materials) else "color_only"


def load_upright(path: Path, up: str = "y", rotation: np.ndarray | None = None) -> tuple[RenderMesh, str]:
    """A mesh file in Z-up world axes and its texture status.

    ``rotation`` (3x3, applied to column vectors) turns the model in its own axes first.
    """
    if up not in UP_AXES:
        raise ValueError(f"up axis must be one of {UP_AXES}, got {up!r}")
    mesh, missing = load_mesh_file(path)
    if rotation is not None:
        mesh = mesh.transformed(rotation)
    if up == "y":
        mesh = y_up_to_z_up(mesh)
    return mesh, texture_status(mesh, missing)


def mesh_file_objects(paths: list[Path], category: str, captions: dict[str, str] | None = None, up: str = "y") -> Iterator[SourceObject]:
    """One object per mesh file; see the module docstring for ids, axes and captions."""
    if up not in UP_AXES:
        raise ValueError(f"up axis must be one of {UP_AXES}, got {up!r}")
    captions = captions or {}
    missing = [str(p) for p in paths if not Path(p).is_file()]
    if missing:
        raise ValueError(f"mesh file(s) not found: {', '.join(missing)}")
    unused = set(captions) - {Path(p).stem for p in paths}
    if unused:
        log.warning("captions given for stems with no mesh file: %s", ", ".join(sorted(unused)))
    counts: dict[str, int] = {}
    for path in map(Path, paths):
        base = slug(path.stem)
        counts[base] = counts.get(base, 0) + 1
        object_id = base if counts[base] == 1 else f"{base}-{counts[base]}"
        name = re.sub(r"[_\-.]+", " ", path.stem).strip() or category
        yield SourceObject(
            id=object_id,
            category=category,
            caption=captions.get(path.stem, ""),
            load=partial(_load_file, path, up, name, category),
            extra={"source": "file", "file": path.name, "name": name},
        )


def _load_file(path: Path, up: str, name: str, category: str) -> tuple[RenderMesh, dict]:
    mesh, texture = load_upright(path, up)
    noun = name if category.lower() in name.lower() else category
    return mesh, {"texture": texture, "caption": default_caption(mesh, noun), "noun": noun}
