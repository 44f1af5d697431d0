"""Turning meshes into an on-disk dataset: normalise, render the fixed poses, write folders and the index.

Every source (procedural chairs, user mesh files, Sweet Home 3D furniture) yields
:class:`SourceObject` items; :func:`build_dataset` does the rest the same way for all of them.
Adding objects to a folder that already holds a dataset merges them into its ``index.json``
(an object with the same id is replaced) and recomputes the hash-based splits over all ids.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from model.data.augment import deformed, draw_deformation
from model.data.colours import default_caption
from model.data.cameras import CAMERA_ANGLE_X, DEFAULT_VIEWS, evaluation_poses, training_poses
from model.data.dataset import INDEX_FILE, ObjectEntry, assign_splits, load_index, write_index, write_object
from model.data.meshes import RenderMesh, normalise
from model.data.raycast import DEFAULT_SUPERSAMPLE, render_views
from model.data.variants import material_variants
from model.nerf.rays import focal_from_fov
from model.nerf.scene import UNIT_BOX

log = logging.getLogger(__name__)

_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass
class RenderSettings:
    """How each object is rendered: training view count, square image size, sub-pixel rays per
    side, how many colour variants of each mesh become objects (1: the mesh as it is), and how
    many deformed copies of each train-split mesh become new shapes (:mod:`model.data.augment`)."""

    views: int = DEFAULT_VIEWS
    resolution: int = 128
    supersample: int = DEFAULT_SUPERSAMPLE
    variants: int = 1
    augment: int = 0

    def __post_init__(self):
        if self.views < 1:
            raise ValueError(f"--views must be at least 1, got {self.views}")
        if self.resolution < 4:
            raise ValueError(f"--res must be at least 4 pixels, got {self.resolution}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be at least 1, got {self.supersample}")
        if self.variants < 1:
            raise ValueError(f"--variants must be at least 1 (1 renders each mesh as it is), got {self.variants}")
        if self.augment < 0:
            raise ValueError(f"--augment must be 0 or more deformed copies per mesh, got {self.augment}")

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class SourceObject:
    """An object to render: its id (a folder name), index fields, and a loader for its mesh.

    ``load`` returns the mesh in Z-up world axes (any position and scale: it is normalised here)
    and the index fields only known once it is loaded: they update ``extra`` (e.g. ``texture``
    status), except ``caption``, a default used when ``caption`` is empty, and ``noun``, what
    captions of colour variants call the object (default: the category). ``extra`` holds
    provenance and attribution (``source``, ``name``, ``creator``, ``license``, ...).
    """

    id: str
    category: str
    caption: str
    load: Callable[[], tuple[RenderMesh, dict]]
    extra: dict = field(default_factory=dict)


def slug(text: str) -> str:
    """A folder-safe id fragment: lower case letters, digits and dashes."""
    cleaned = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return cleaned or "object"


def dataset_poses(views: int) -> tuple[np.ndarray, list[str]]:
    """Training poses followed by the fixed evaluation poses, and the split of each frame."""
    train, test = training_poses(views), evaluation_poses()
    return np.concatenate([train, test]), ["train"] * len(train) + ["test"] * len(test)


def render_object(mesh: RenderMesh, settings: RenderSettings, desc: str = "rendering") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Render a normalised mesh from all dataset poses: ``(images [V, R, R, 4] uint8, c2w [V, 4, 4], frame splits)``."""
    c2w, splits = dataset_poses(settings.views)
    size = settings.resolution
    images = render_views(mesh, c2w, size, size, focal_from_fov(size, CAMERA_ANGLE_X), settings.supersample, desc)
    return images, c2w, splits


def build_dataset(out: Path, objects: Iterable[SourceObject], settings: RenderSettings, total: int | None = None) -> list[ObjectEntry]:
    """Render every object into ``out/<id>/`` and write ``out/index.json``; returns all index entries.

    The index is rewritten after each object, so an interrupted run leaves a usable dataset.
    With ``settings.augment`` each source that falls in the train split is followed by that many
    deformed copies of its mesh.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    entries: dict[str, ObjectEntry] = {}
    if (out / INDEX_FILE).exists():
        entries = {entry.id: entry for entry in load_index(out)}
        log.info("adding to the existing dataset in %s (%d objects)", out, len(entries))
    if settings.augment:
        objects = with_augmented_copies(list(objects), settings.augment, entries)
        total = len(objects)
    added: set[str] = set()
    for item in tqdm(objects, total=total, desc="objects", unit="object"):
        if not _ID_PATTERN.match(item.id):
            raise ValueError(f"object id {item.id!r} is not a safe folder name (letters, digits, '.', '_', '-')")
        if item.id in added:
            raise ValueError(f"two objects share the id {item.id!r}; give them distinct names")
        mesh, learned = item.load()
        mesh = normalise(mesh)
        extra = {**item.extra, **learned}
        fallback = extra.pop("caption", "") or f"a {item.category}"
        noun = extra.pop("noun", item.category)
        for k, variant in enumerate(material_variants(mesh, settings.variants, item.id)):
            object_id = item.id if k == 0 else f"{item.id}-v{k}"
            caption = (item.caption or fallback) if k == 0 else default_caption(variant, noun)
            fields = {**extra, "shape_id": item.id, "variant": k} if settings.variants > 1 else extra
            images, c2w, frame_splits = render_object(variant, settings, desc=object_id)
            write_object(
                out / object_id, images, c2w, frame_splits, CAMERA_ANGLE_X, UNIT_BOX.to_aabb(), variant.to_trimesh(), settings.to_json()
            )
            added.add(object_id)
            entries[object_id] = ObjectEntry(object_id, "train", item.category, caption, fields)
            _write_with_splits(out, entries)
            log.info("wrote %s: %d views at %dx%d (%s)", object_id, len(images), settings.resolution, settings.resolution, caption)
    if not added:
        raise ValueError("no objects to render")
    return _write_with_splits(out, entries)


def split_group(object_id: str, extra: dict) -> str:
    """What an object is split with: colour variants of one mesh and deformed copies of it share
    the source mesh's split, so no test shape (nor a deformation of one) is seen in training."""
    return str(extra.get("augmented_from", extra.get("shape_id", object_id)))


def with_augmented_copies(objects: list[SourceObject], copies: int, existing: dict[str, ObjectEntry]) -> list[SourceObject]:
    """``objects`` with ``copies`` deformed copies (ids ``<id>-aug1``, ...) after each one in the train split."""
    groups = {i: split_group(i, e.extra) for i, e in existing.items()} | {item.id: item.id for item in objects}
    splits = assign_splits(groups, groups=groups)
    out = []
    for item in objects:
        out.append(item)
        if splits[item.id] != "train":
            continue
        for j in range(1, copies + 1):
            copy_id = f"{item.id}-aug{j}"
            deformation = draw_deformation(copy_id)
            out.append(
                SourceObject(
                    id=copy_id, category=item.category, caption=item.caption, load=partial(_deformed_load, item.load, deformation),
                    extra={**item.extra, "augmented_from": item.id, "deformation": deformation.to_json()},
                )
            )
    return out


def _deformed_load(load: Callable[[], tuple[RenderMesh, dict]], deformation) -> tuple[RenderMesh, dict]:
    mesh, learned = load()
    return deformed(mesh, deformation), learned


def _write_with_splits(out: Path, entries: dict[str, ObjectEntry]) -> list[ObjectEntry]:
    splits = assign_splits(entries, groups={i: split_group(i, e.extra) for i, e in entries.items()})
    for object_id, entry in entries.items():
        entry.split = splits[object_id]
    write_index(out, entries.values())
    return sorted(entries.values(), key=lambda e: e.id)
