"""The on-disk multi-view dataset format: writing it and reading it back.

Layout (NeRF-synthetic convention, one folder per object)::

    DIR/index.json                 {"format": 1, "objects": [{"id", "split", "category", "caption",
                                    "source", ...attribution: "name", "creator", "license", "texture"}]}
    DIR/<id>/transforms.json       {"camera_angle_x" (or "fl_x", "fl_y", "cx", "cy"), "w", "h",
                                    "aabb": [[x, y, z], [x, y, z]],
                                    "render": {"views", "resolution", "supersample"} (provenance),
                                    "frames": [{"file_path": "images/train_000.png",
                                                "transform_matrix": 4x4 camera-to-world,
                                                "split": "train" | "val" | "test",
                                                optional per-frame "fl_x", "fl_y", "cx", "cy"}]}
    DIR/<id>/images/*.png          8-bit RGBA, straight alpha, transparent background
    DIR/<id>/mesh.ply              normalised ground-truth mesh in the cameras' coordinates (optional)

Poses use the OpenGL convention of :mod:`model.nerf.rays` (camera looks down -Z, +Y up); the world is
Z-up with every object inside the scene box ``aabb`` (see :mod:`model.data.cameras`). Intrinsics are
a pinhole: ``camera_angle_x`` (square pixels, centred principal point) or nerfstudio's ``fl_x``,
``fl_y``, ``cx``, ``cy`` in pixels, at the top level or per frame.

Object splits (train/val/test) come from a hash of the object id, so they do not depend on the
order objects are added; see :func:`assign_splits`.

Images are read and written with **Pillow**.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from model.nerf.rays import Intrinsics
from model.nerf.scene import SceneBox

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
INDEX_FILE = "index.json"
TRANSFORMS_FILE = "transforms.json"
MESH_FILE = "mesh.ply"
IMAGES_DIR = "images"
OBJECT_SPLITS = ("train", "val", "test")
FRAME_SPLITS = ("train", "val", "test")
# Fractions of objects in train and val (test gets the rest).
_SPLIT_FRACTIONS = (0.8, 0.1)


class DatasetError(ValueError):
    """A dataset file is missing or invalid; the message says which file and what to do."""


@dataclass
class ObjectEntry:
    """One object of ``index.json``: the fixed fields, plus attribution and provenance in ``extra``."""

    id: str
    split: str
    category: str
    caption: str
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"id": self.id, "split": self.split, "category": self.category, "caption": self.caption, **self.extra}

    @classmethod
    def from_json(cls, record: dict, where: Path) -> ObjectEntry:
        if not isinstance(record, dict):
            raise DatasetError(f"{where}: each entry of 'objects' must be a JSON object, got {record!r}")
        missing = [key for key in ("id", "split", "category", "caption") if key not in record]
        if missing:
            raise DatasetError(f"{where}: object entry {record!r} lacks {', '.join(missing)}; rebuild the index")
        if record["split"] not in OBJECT_SPLITS:
            raise DatasetError(f"{where}: object {record['id']!r} has split {record['split']!r}; use one of {OBJECT_SPLITS}")
        extra = {k: v for k, v in record.items() if k not in ("id", "split", "category", "caption")}
        return cls(str(record["id"]), record["split"], str(record["category"]), str(record["caption"]), extra)


@dataclass
class Views:
    """Posed RGBA views of one object.

    ``images [V, H, W, 4]`` float32 in [0, 1] with straight alpha (opaque for images without
    alpha), ``c2w [V, 4, 4]`` float32, ``cameras`` one pinhole per view (all of one image size),
    ``scene`` the object's scene box, ``files`` the image paths relative to the object folder,
    ``mesh_path`` the ground-truth mesh if present.
    """

    images: torch.Tensor
    c2w: torch.Tensor
    cameras: list[Intrinsics]
    scene: SceneBox
    files: list[str]
    mesh_path: Path | None

    @property
    def width(self) -> int:
        return self.cameras[0].width

    @property
    def height(self) -> int:
        return self.cameras[0].height

    @property
    def camera(self) -> Intrinsics:
        """The one camera every view shares; an error when views differ in intrinsics."""
        if any(c != self.cameras[0] for c in self.cameras[1:]):
            raise DatasetError("these views have different intrinsics; use views.cameras per view")
        return self.cameras[0]

    @property
    def has_alpha(self) -> bool:
        """Whether any image has a transparent pixel: then alpha gives masks (and a visual hull)."""
        return bool((self.images[..., 3] < 1.0).any())

    def subset(self, index) -> "Views":
        """The views at ``index`` (a slice or a list of view numbers)."""
        picks = list(range(len(self.files)))[index] if isinstance(index, slice) else list(index)
        return Views(self.images[picks], self.c2w[picks], [self.cameras[i] for i in picks], self.scene, [self.files[i] for i in picks], self.mesh_path)


class Index(list):
    """The objects of ``index.json`` (a list of :class:`ObjectEntry`) with lookups by id and split."""

    def ids(self, split: str | None = None) -> list[str]:
        return [entry.id for entry in self if split is None or entry.split == split]

    def get(self, object_id: str) -> ObjectEntry:
        for entry in self:
            if entry.id == object_id:
                return entry
        raise KeyError(f"no object {object_id!r} in the index")


# ---------------------------------------------------------------------------------------------
# Validation


def validate_views(images, c2w) -> None:
    """Reject views that cannot be trained on: wrong shapes or NaN/Inf values.

    ``images`` is ``[V, H, W, 3 or 4]`` and ``c2w`` ``[V, 4, 4]`` (or ``[V, 3, 4]``), as torch
    tensors or numpy arrays. Raises :class:`DatasetError` saying what is wrong.
    """
    images = torch.as_tensor(np.asarray(images) if not torch.is_tensor(images) else images)
    c2w = torch.as_tensor(np.asarray(c2w) if not torch.is_tensor(c2w) else c2w)
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise DatasetError(f"images must be [V, H, W, 3 or 4], got shape {tuple(images.shape)}")
    if c2w.ndim != 3 or tuple(c2w.shape[1:]) not in ((4, 4), (3, 4)):
        raise DatasetError(f"poses must be [V, 4, 4] camera-to-world matrices, got shape {tuple(c2w.shape)}")
    if images.shape[0] != c2w.shape[0]:
        raise DatasetError(f"{images.shape[0]} images but {c2w.shape[0]} poses; give one pose per image")
    if images.is_floating_point():
        bad = (~torch.isfinite(images)).flatten(1).any(dim=1).nonzero().flatten().tolist()
        if bad:
            raise DatasetError(f"images {bad} contain NaN or Inf values; fix or drop those images")
    bad = (~torch.isfinite(c2w)).flatten(1).any(dim=1).nonzero().flatten().tolist()
    if bad:
        raise DatasetError(f"poses {bad} contain NaN or Inf values; fix or drop those views")


# ---------------------------------------------------------------------------------------------
# Splits


def _unit_hash(object_id: str) -> float:
    digest = hashlib.sha256(object_id.encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "big") / 2.0**64


def assign_splits(ids: Iterable[str], groups: dict[str, str] | None = None) -> dict[str, str]:
    """Deterministic object splits: about 80% train, 10% val, 10% test from a hash of each id.

    ``groups`` maps ids to a group (colour variants of one mesh share their ``shape_id``); a group
    is split as one object, so all its members land in the same split. With three or more groups
    every split gets at least one: an empty split takes the group whose hash lies closest to it
    from the largest split. The result depends only on the set of ids and their groups.
    """
    ids = sorted(set(ids))
    group_of = {i: (groups or {}).get(i, i) for i in ids}
    by_group = _split_groups(group_of.values())
    return {i: by_group[group_of[i]] for i in ids}


def _split_groups(groups: Iterable[str]) -> dict[str, str]:
    keys = {group: _unit_hash(group) for group in sorted(set(groups))}
    train_end, val_end = _SPLIT_FRACTIONS[0], sum(_SPLIT_FRACTIONS)
    splits = {i: "train" if h < train_end else "val" if h < val_end else "test" for i, h in keys.items()}
    if len(keys) >= 3:
        centres = {"train": 0.5 * train_end, "val": 0.5 * (train_end + val_end), "test": 0.5 * (val_end + 1.0)}
        for wanted in ("val", "test", "train"):
            if wanted in splits.values():
                continue
            members = {s: [i for i in splits if splits[i] == s] for s in OBJECT_SPLITS}
            donor = max((s for s in OBJECT_SPLITS if s != wanted), key=lambda s: (len(members[s]), s))
            chosen = min(members[donor], key=lambda i: (abs(keys[i] - centres[wanted]), i))
            splits[chosen] = wanted
    return splits


# ---------------------------------------------------------------------------------------------
# Writing


def write_object(
    folder: Path,
    images: np.ndarray,
    c2w: np.ndarray,
    frame_splits: Sequence[str],
    camera: float | Sequence[Intrinsics],
    aabb: Sequence[Sequence[float]],
    mesh=None,
    render: dict | None = None,
    extra: dict | None = None,
) -> None:
    """Write one object folder: PNGs, ``transforms.json`` (written last) and optionally ``mesh.ply``.

    ``images`` is 8-bit RGBA ``[V, H, W, 4]``, ``c2w`` ``[V, 4, 4]``, ``frame_splits`` one of
    ``FRAME_SPLITS`` per view, ``camera`` a horizontal field of view in radians (centred, square
    pixels) or one :class:`Intrinsics` per view (written once when all agree, else per frame),
    ``mesh`` a trimesh mesh or ``None``, ``render`` the render settings and ``extra`` any other
    provenance, both kept in ``transforms.json``.
    """
    validate_views(images, c2w)
    if images.dtype != np.uint8 or images.shape[-1] != 4:
        raise ValueError("write_object expects 8-bit RGBA images [V, H, W, 4]")
    folder = Path(folder)
    (folder / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
    counters = dict.fromkeys(FRAME_SPLITS, 0)
    frames = []
    for image, pose, split in zip(images, c2w, frame_splits):
        if split not in FRAME_SPLITS:
            raise ValueError(f"frame split must be one of {FRAME_SPLITS}, got {split!r}")
        name = f"{IMAGES_DIR}/{split}_{counters[split]:03d}.png"
        counters[split] += 1
        Image.fromarray(image, mode="RGBA").save(folder / name)
        frames.append({"file_path": name, "split": split, "transform_matrix": np.asarray(pose, dtype=float).tolist()})
    if mesh is not None:
        mesh.export(folder / MESH_FILE)
    if isinstance(camera, (int, float)):
        intrinsics = {"camera_angle_x": float(camera)}
    else:
        cameras = list(camera)
        if len(cameras) != len(frames):
            raise ValueError(f"{len(cameras)} cameras for {len(frames)} images; give one per image")
        pinhole = [{"fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy} for c in cameras]
        if all(p == pinhole[0] for p in pinhole):
            intrinsics = pinhole[0]
        else:
            intrinsics = {}
            for frame, values in zip(frames, pinhole):
                frame.update(values)
    transforms = {
        **intrinsics,
        "w": int(images.shape[2]),
        "h": int(images.shape[1]),
        "aabb": [list(map(float, corner)) for corner in aabb],
        **({"render": render} if render else {}),
        **(extra or {}),
        "frames": frames,
    }
    (folder / TRANSFORMS_FILE).write_text(json.dumps(transforms, indent=1))


def write_index(root: Path, entries: Iterable[ObjectEntry]) -> None:
    """Write ``index.json`` (entries sorted by id), replacing any earlier one atomically."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    payload = {"format": FORMAT_VERSION, "objects": [e.to_json() for e in sorted(entries, key=lambda e: e.id)]}
    temporary = root / (INDEX_FILE + ".tmp")
    temporary.write_text(json.dumps(payload, indent=1, ensure_ascii=False))
    temporary.replace(root / INDEX_FILE)


# ---------------------------------------------------------------------------------------------
# Reading


def _read_json(path: Path, hint: str) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path} not found; {hint}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path} is not valid JSON ({error}); {hint}") from error
    if not isinstance(data, dict):
        raise DatasetError(f"{path} must hold a JSON object; {hint}")
    return data


def load_index(root: Path) -> Index:
    """The objects listed in ``root/index.json``."""
    path = Path(root) / INDEX_FILE
    hint = "build a dataset with `hypnerf data synth`, `import-meshes` or `import-sh3d`"
    data = _read_json(path, hint)
    if data.get("format") != FORMAT_VERSION:
        raise DatasetError(f"{path}: format {data.get('format')!r} is not {FORMAT_VERSION}; rebuild the dataset")
    objects = data.get("objects")
    if not isinstance(objects, list):
        raise DatasetError(f"{path}: 'objects' must be a list; {hint}")
    index = Index(ObjectEntry.from_json(record, path) for record in objects)
    seen: set[str] = set()
    for entry in index:
        if entry.id in seen:
            raise DatasetError(f"{path}: object id {entry.id!r} appears twice; ids must be unique")
        seen.add(entry.id)
    return index


def _read_image(path: Path, transforms: Path) -> np.ndarray:
    """An image file as float32 RGBA in [0, 1]; RGB and grey images get an opaque alpha."""
    if not path.is_file():
        raise DatasetError(f"{path} (listed in {transforms}) is missing; re-render the object or fix its file_path")
    try:
        with Image.open(path) as image:
            image.load()
            if image.mode in ("I;16", "I;16B", "I", "F"):
                raise DatasetError(f"{path} has mode {image.mode}; convert it to 8-bit RGBA or RGB")
            array = np.asarray(image.convert("RGBA"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, SyntaxError) as error:
        raise DatasetError(f"{path} cannot be read as an image ({error}); re-render the object") from error
    return array


def _frame_file(folder: Path, frame: dict, transforms: Path) -> str:
    name = frame.get("file_path")
    if not isinstance(name, str) or not name:
        raise DatasetError(f"{transforms}: a frame lacks 'file_path'; every frame needs an image path")
    # NeRF-synthetic scenes name images without an extension ("./train/r_0"): .png is implied.
    if not (folder / name).exists() and not Path(name).suffix:
        name = name + ".png"
    return name


def _frame_pose(frame: dict, transforms: Path, number: int) -> np.ndarray:
    try:
        pose = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except KeyError:
        raise DatasetError(f"{transforms}: frame {number} lacks 'transform_matrix'") from None
    except (TypeError, ValueError) as error:
        raise DatasetError(f"{transforms}: frame {number} 'transform_matrix' is not numeric ({error})") from error
    if pose.shape != (4, 4):
        raise DatasetError(f"{transforms}: frame {number} 'transform_matrix' has shape {pose.shape}; it must be 4x4")
    if not np.isfinite(pose).all():
        raise DatasetError(f"{transforms}: frame {number} 'transform_matrix' contains NaN or Inf; fix or drop the frame")
    return pose


def _aabb(transforms_data: dict, transforms: Path) -> np.ndarray:
    try:
        aabb = np.asarray(transforms_data["aabb"], dtype=np.float64)
    except KeyError:
        raise DatasetError(
            f"{transforms} lacks 'aabb'; add the scene box, e.g. \"aabb\": [[-0.5,-0.5,-0.5],[0.5,0.5,0.5]]"
        ) from None
    except (TypeError, ValueError) as error:
        raise DatasetError(f"{transforms}: 'aabb' is not numeric ({error})") from error
    if aabb.shape != (2, 3) or not np.isfinite(aabb).all() or not (aabb[0] < aabb[1]).all():
        raise DatasetError(f"{transforms}: 'aabb' must be [[xmin,ymin,zmin],[xmax,ymax,zmax]] with min < max")
    return SceneBox.from_aabb(aabb)


def _number(source: dict, key: str, where: str) -> float | None:
    value = source.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(f"{where}: {key!r} must be a finite number, got {value!r}")
    return float(value)


def frame_intrinsics(data: dict, frame: dict, width: int, height: int, where: str) -> Intrinsics:
    """The pinhole of one frame: its own ``fl_x``/``fl_y``/``cx``/``cy`` over the file's, else
    ``camera_angle_x`` (and ``camera_angle_y`` for non-square pixels) with a centred principal point."""

    def pick(key: str) -> float | None:
        value = _number(frame, key, where)
        return value if value is not None else _number(data, key, where)

    fx, fy = pick("fl_x"), pick("fl_y")
    if fx is None:
        angle = pick("camera_angle_x")
        if angle is None or not 0.0 < angle < math.pi:
            raise DatasetError(f"{where}: give 'camera_angle_x' (horizontal field of view in radians, in (0, pi)) or 'fl_x' in pixels; got {angle!r}")
        fx = 0.5 * width / math.tan(0.5 * angle)
    if fy is None:
        angle_y = pick("camera_angle_y")
        fy = 0.5 * height / math.tan(0.5 * angle_y) if angle_y is not None else fx
    cx, cy = pick("cx"), pick("cy")
    try:
        return Intrinsics(width, height, fx, fy, 0.5 * width if cx is None else cx, 0.5 * height if cy is None else cy)
    except ValueError as error:
        raise DatasetError(f"{where}: {error}") from error


def load_views(folder: Path, split: str | None = "train") -> Views:
    """Load one object's views of a frame split (``"train"``, ``"test"``, or ``None`` for all)."""
    if split is not None and split not in FRAME_SPLITS:
        raise ValueError(f"split must be one of {FRAME_SPLITS} or None, got {split!r}")
    folder = Path(folder)
    transforms = folder / TRANSFORMS_FILE
    hint = "the object folder is incomplete: re-render it"
    data = _read_json(transforms, hint)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{transforms}: 'frames' must be a non-empty list; {hint}")
    # Frames without a split are training frames, as in single-split NeRF-synthetic files.
    chosen = [(n, f) for n, f in enumerate(frames) if isinstance(f, dict) and (split is None or f.get("split", "train") == split)]
    if not chosen:
        raise DatasetError(f"{transforms} has no frames with split {split!r}; {hint}")
    scene = _aabb(data, transforms)
    files = [_frame_file(folder, frame, transforms) for _, frame in chosen]
    poses = np.stack([_frame_pose(frame, transforms, number) for number, frame in chosen])
    images = [_read_image(folder / name, transforms) for name in files]
    height, width = images[0].shape[:2]
    expected = (data.get("h", height), data.get("w", width))
    if not all(isinstance(size, int) and size > 0 for size in expected):
        raise DatasetError(f"{transforms}: 'w' and 'h' must be positive integers, got {expected[1]!r} and {expected[0]!r}")
    for name, image in zip(files, images):
        if image.shape[:2] != expected:
            raise DatasetError(
                f"{folder / name} is {image.shape[1]}x{image.shape[0]} but {transforms} says "
                f"{expected[1]}x{expected[0]}; all images of an object must share that size"
            )
    image_tensor = torch.from_numpy(np.stack(images))
    c2w = torch.from_numpy(poses.astype(np.float32))
    validate_views(image_tensor, c2w)
    cameras = [frame_intrinsics(data, frame, int(expected[1]), int(expected[0]), f"{transforms} frame {number}") for number, frame in chosen]
    mesh = folder / MESH_FILE
    log.debug("loaded %d %s views of %s at %dx%d", len(files), split or "all", folder, expected[1], expected[0])
    return Views(images=image_tensor, c2w=c2w, cameras=cameras, scene=scene, files=files, mesh_path=mesh if mesh.is_file() else None)

