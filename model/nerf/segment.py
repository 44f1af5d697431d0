"""An object's RGBA image from what a user uploads: an RGBA image, an image plus a mask, or a
plain photo whose background is segmented here (with **OpenCV**'s GrabCut).

Rules, in order:

1. An image with an alpha channel that has transparent pixels keeps its alpha.
2. A mask (``[H, W]``, nonzero or > 0.5 = object) given beside the image becomes its alpha.
3. A plain photo is segmented: a background colour model is seeded from a border strip of the
   image (the object is assumed not to touch the border, as in a product photo or a centred crop),
   or from everything outside a box the user draws around the object (as SAM is prompted),
   (GrabCut's background colour mixture is initialised from those pixels), then GrabCut labels the
   rest. Specks are dropped (components under 5% of the largest one's area).
   The result is rejected (:class:`SegmentationError`, saying to send a mask or an RGBA image)
   when the object covers too little or too much of the image: what GrabCut does when the
   object's colours cannot be told from the border's.

GrabCut is a classical graph-cut method, not a learned segmenter like SAM: in a cluttered scene
without a box, clutter inside the border strip is kept as object (measured in BENCHMARKS.md); a
box helps, and a mask is best.
"""

from __future__ import annotations

import numpy as np

MIN_FOREGROUND = 0.02
MAX_FOREGROUND = 0.85
BORDER_FRACTION = 0.04
GRABCUT_ITERATIONS = 5


class SegmentationError(ValueError):
    """The photo's object could not be separated from its background; the message says what to send instead."""


def _as_float_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        raise SegmentationError(f"an image must be [H, W, 3] (RGB) or [H, W, 4] (RGBA), got shape {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise SegmentationError(f"the image is {image.shape[1]}x{image.shape[0]} pixels; send at least 8x8")
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    image = image.astype(np.float32)
    if not np.isfinite(image).all():
        raise SegmentationError("the image contains NaN or Inf values")
    return np.clip(image, 0.0, 1.0)


def object_rgba(image: np.ndarray, mask: np.ndarray | None = None, box: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, str]:
    """Straight-alpha RGBA ``[H, W, 4]`` float32 in [0, 1] of the object in ``image`` (uint8 or float
    ``[H, W, 3 or 4]``), and how its alpha was obtained: ``"alpha"``, ``"mask"`` or ``"grabcut"``.
    ``box`` (``x0, y0, x1, y1`` in pixels, the object inside) guides the segmentation of a plain photo."""
    image = _as_float_image(image)
    rgb = image[..., :3]
    if mask is not None:
        mask = np.asarray(mask)
        if mask.ndim == 3:
            mask = mask[..., -1] if mask.shape[-1] in (2, 4) else mask.max(axis=-1)
        if mask.shape != rgb.shape[:2]:
            raise SegmentationError(f"the mask is {mask.shape[1]}x{mask.shape[0]} but the image {rgb.shape[1]}x{rgb.shape[0]}; send a mask of the image's size")
        alpha = (mask.astype(np.float32) / (255.0 if mask.dtype == np.uint8 else 1.0)) > 0.5
        _check_coverage(alpha, "the mask")
        return np.concatenate([rgb, alpha[..., None].astype(np.float32)], axis=-1), "mask"
    if image.shape[-1] == 4 and (image[..., 3] < 1.0).any():
        _check_coverage(image[..., 3] > 0.5, "the image's alpha")
        return image, "alpha"
    return np.concatenate([rgb, segment_photo(rgb, box)[..., None].astype(np.float32)], axis=-1), "grabcut"


def _check_coverage(foreground: np.ndarray, what: str) -> None:
    fraction = float(foreground.mean())
    if fraction < MIN_FOREGROUND:
        raise SegmentationError(f"{what} covers {fraction:.1%} of the image: too little to show an object; send a mask that covers it")


def segment_photo(rgb: np.ndarray, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Boolean object mask ``[H, W]`` of a plain photo ``[H, W, 3]`` in [0, 1] (see the module
    docstring); with a ``box`` (``x0, y0, x1, y1``) everything outside it is background."""
    import cv2

    height, width = rgb.shape[:2]
    border = max(2, int(round(BORDER_FRACTION * min(height, width))))
    bgr = np.ascontiguousarray((rgb[..., ::-1] * 255.0 + 0.5).astype(np.uint8))
    labels = np.full((height, width), cv2.GC_PR_FGD, dtype=np.uint8)
    edge = np.ones((height, width), dtype=bool)
    if box is None:
        edge[border:-border, border:-border] = False
    else:
        x0, y0, x1, y1 = (int(round(v)) for v in box)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
        if x1 - x0 < 2 or y1 - y0 < 2:
            raise SegmentationError(f"the box {box} leaves no part of the {width}x{height} image; give x0 < x1 and y0 < y1 inside it")
        edge[y0:y1, x0:x1] = False
    labels[edge] = cv2.GC_BGD
    background, foreground = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(bgr, labels, None, background, foreground, GRABCUT_ITERATIONS, cv2.GC_INIT_WITH_MASK)
    mask = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    mask = _main_components(mask.astype(np.uint8))
    fraction = float(mask.mean())
    if not MIN_FOREGROUND <= fraction <= MAX_FOREGROUND:
        raise SegmentationError(
            f"could not separate the object from the background (segmented {fraction:.0%} of the image); "
            "send an RGBA image with a transparent background or the image with a mask"
        )
    return mask


def _main_components(mask: np.ndarray, keep: float = 0.05) -> np.ndarray:
    """The 8-connected components of a uint8 mask at least ``keep`` times the largest one's area
    (drops specks; gaps inside the object, like those of a slatted back, stay background)."""
    import cv2

    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count <= 1:
        return np.zeros(mask.shape, dtype=bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    kept = 1 + np.flatnonzero(areas >= keep * areas.max())
    return np.isin(labels, kept)
