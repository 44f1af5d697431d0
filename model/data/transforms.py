"""Import a posed multi-view scene a user brings, into this project's dataset format (one object).

Two layouts are read:

* **NeRF-synthetic**: ``transforms_train.json``, ``transforms_val.json``, ``transforms_test.json``,
  each with ``camera_angle_x`` and frames whose ``file_path`` has no extension (``./train/r_0``
  means ``train/r_0.png``), RGBA PNGs. The frame split is the file's (val frames stay ``val``).
* **nerfstudio**: one ``transforms.json`` with pinhole intrinsics ``fl_x``, ``fl_y``, ``cx``,
  ``cy``, ``w``, ``h`` (or ``camera_angle_x``), optionally per frame, and ``file_path`` with its
  extension. Frames without a ``split`` are split by ``test_every``. Only an undistorted pinhole
  is supported: a ``camera_model`` other than a pinhole, or any non-zero distortion coefficient,
  is rejected (undistort the images first, e.g. with COLMAP's ``image_undistorter``).

Poses keep the files' OpenGL camera-to-world convention. The scene box is, in order: ``aabb``
given by the caller, the file's own ``aabb``, the convention's (NeRF-synthetic objects lie within
[-1.5, 1.5]^3), or one derived from the cameras (a cube around the point nearest to every optical
axis, as large as the sphere every view sees whole); the report says which. ``downscale`` shrinks
images by an integer factor with area averaging of premultiplied colour (so transparent pixels
leave no fringe), cropping a remainder row or column and scaling the intrinsics to match.
Images are read and written with Pillow.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from model.data.dataset import DatasetError, ObjectEntry, frame_intrinsics, write_index, write_object
from model.nerf.rays import Intrinsics
from model.nerf.scene import SceneBox

log = logging.getLogger(__name__)

NERF_SYNTHETIC_HALF_SIDE = 1.5
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE", "RADIAL", "SIMPLE_RADIAL")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _read(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path} cannot be read as JSON ({error})") from error
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise DatasetError(f"{path} must be a JSON object with a non-empty 'frames' list")
    return data


def _check_pinhole(data: dict, frame: dict, where: str) -> None:
    model = frame.get("camera_model", data.get("camera_model", "PINHOLE"))
    if model not in PINHOLE_MODELS:
        raise DatasetError(f"{where}: camera_model {model!r} is not supported; only undistorted pinhole cameras are (undistort the images first)")
    for key in DISTORTION_KEYS:
        value = frame.get(key, data.get(key, 0.0))
        if value not in (0, 0.0, None):
            raise DatasetError(
                f"{where}: distortion {key}={value} is not supported; only undistorted pinhole cameras are "
                "(undistort the images first, e.g. with COLMAP's image_undistorter)"
            )


def _image(folder: Path, file_path: str, where: str) -> np.ndarray:
    path = folder / file_path
    if not path.is_file() and not Path(file_path).suffix:
        path = path.with_name(path.name + ".png")
    if not path.is_file():
        raise DatasetError(f"{where}: image {file_path!r} not found under {folder}")
    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGBA"), dtype=np.uint8)
    except (UnidentifiedImageError, OSError) as error:
        raise DatasetError(f"{where}: {path} cannot be read as an image ({error})") from error


def downscale_rgba(image: np.ndarray, factor: int) -> np.ndarray:
    """8-bit straight-alpha RGBA ``[H, W, 4]`` shrunk by ``factor`` (area average of premultiplied colour)."""
    if factor == 1:
        return image
    h, w = image.shape[0] // factor * factor, image.shape[1] // factor * factor
    rgba = image[:h, :w].astype(np.float64) / 255.0
    alpha = rgba[..., 3:]
    blocks = np.concatenate([rgba[..., :3] * alpha, alpha], axis=-1).reshape(h // factor, factor, w // factor, factor, 4).mean(axis=(1, 3))
    a = blocks[..., 3:]
    rgb = np.where(a > 0, blocks[..., :3] / np.maximum(a, 1e-12), 0.0)
    return (np.concatenate([rgb, a], axis=-1) * 255.0 + 0.5).clip(0, 255).astype(np.uint8)


def camera_box(c2w: np.ndarray, cameras: list[Intrinsics]) -> SceneBox:
    """A cube around the point closest (least squares) to every camera's optical axis, with half its
    side the radius of the largest sphere there that every camera sees whole."""
    origins, axes = c2w[:, :3, 3], -c2w[:, :3, 2]
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    centre = np.linalg.lstsq(projectors.sum(0), np.einsum("nij,nj->i", projectors, origins), rcond=None)[0]
    distance = np.linalg.norm(origins - centre, axis=1).min()
    half_fov = min(min(math.atan(0.5 * c.width / c.fx), math.atan(0.5 * c.height / c.fy)) for c in cameras)
    radius = float(distance * math.sin(half_fov))
    if not math.isfinite(radius) or radius <= 0:
        raise DatasetError("the cameras do not look at a common point; give the scene box with --aabb")
    return SceneBox.cube(radius, tuple(float(v) for v in centre))


def _frames(source: Path, test_every: int) -> tuple[str, list[tuple[dict, dict, str]]]:
    """The layout's name and its frames as ``(file data, frame, split)``."""
    if (source / "transforms_train.json").is_file():
        frames = []
        for split in ("train", "val", "test"):
            path = source / f"transforms_{split}.json"
            if path.is_file():
                data = _read(path)
                frames += [(data, frame, split) for frame in data["frames"]]
        return "nerf-synthetic", frames
    if (source / "transforms.json").is_file():
        if test_every < 2:
            raise DatasetError(f"--test-every must be at least 2, got {test_every}")
        data = _read(source / "transforms.json")
        frames = []
        for number, frame in enumerate(data["frames"]):
            split = frame.get("split") if isinstance(frame, dict) else None
            frames.append((data, frame, split if split in ("train", "val", "test") else ("test" if number % test_every == 0 else "train")))
        return "nerfstudio", frames
    raise DatasetError(f"{source} holds neither transforms_train.json (NeRF-synthetic) nor transforms.json (nerfstudio)")


def import_transforms(
    source: Path,
    out: Path,
    *,
    object_id: str | None = None,
    category: str = "object",
    downscale: int = 1,
    aabb=None,
    test_every: int = 8,
) -> dict:
    """Import the scene in ``source`` as one object of the dataset ``out``; returns what was done."""
    source, out = Path(source), Path(out)
    if downscale < 1:
        raise DatasetError(f"--downscale must be a positive integer, got {downscale}")
    layout, frames = _frames(source, test_every)
    images, poses, cameras, splits = [], [], [], []
    for number, (data, frame, split) in enumerate(frames):
        where = f"{source} frame {number}"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DatasetError(f"{where}: each frame needs a 'file_path'")
        _check_pinhole(data, frame, where)
        pose = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise DatasetError(f"{where}: 'transform_matrix' must be a finite 4x4 camera-to-world matrix")
        image = _image(source, frame["file_path"], where)
        height, width = image.shape[:2]
        size = (int(frame.get("w", data.get("w", width))), int(frame.get("h", data.get("h", height))))
        if size != (width, height):
            raise DatasetError(f"{where}: the file says {size[0]}x{size[1]} but the image is {width}x{height}")
        camera = frame_intrinsics(data, frame, width, height, where)
        if downscale > 1:
            image = downscale_rgba(image, downscale)
            camera = Intrinsics(image.shape[1], image.shape[0], camera.fx / downscale, camera.fy / downscale, camera.cx / downscale, camera.cy / downscale)
        images.append(image)
        poses.append(pose)
        cameras.append(camera)
        splits.append(split)
    if len({im.shape for im in images}) != 1:
        raise DatasetError(f"{source}: images differ in size; all frames of a scene must share one size")
    c2w = np.stack(poses)
    if aabb is not None:
        box, box_source = SceneBox.from_aabb(aabb), "given"
    elif "aabb" in frames[0][0]:
        box, box_source = SceneBox.from_aabb(frames[0][0]["aabb"]), "the file's aabb"
    elif layout == "nerf-synthetic":
        box, box_source = SceneBox.cube(NERF_SYNTHETIC_HALF_SIDE), "NeRF-synthetic convention, objects within [-1.5, 1.5]^3"
    else:
        box, box_source = camera_box(c2w, cameras), "derived from the cameras"
    object_id = object_id or source.resolve().name
    if "train" not in splits:
        raise DatasetError(f"{source}: no training frames")
    provenance = {"source": {"path": str(source.resolve()), "layout": layout, "downscale": downscale, "aabb_source": box_source}}
    write_object(out / object_id, np.stack(images), c2w, splits, cameras, box.to_aabb(), extra=provenance)
    write_index(out, [ObjectEntry(object_id, "train", category, "", {"source": f"import-transforms ({layout})"})])
    counts = {s: splits.count(s) for s in ("train", "val", "test") if s in splits}
    return {
        "id": object_id, "layout": layout, "frames": len(frames), "splits": counts, "width": images[0].shape[1], "height": images[0].shape[0],
        "aabb": box.to_aabb(), "aabb_source": box_source,
    }
