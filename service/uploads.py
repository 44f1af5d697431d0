"""Decoding uploaded images safely (Pillow): known formats only, a decompression-bomb guard, RGBA out.

Pillow reads the header before any pixel, so the format check (415) and the pixel cap (413) are
decided on the header alone; ``Image.MAX_IMAGE_PIXELS`` is the service's cap, and Pillow's
``DecompressionBombWarning`` (between the cap and twice it) is raised as the same error as its
``DecompressionBombError`` (above twice it).
"""

from __future__ import annotations

import io
import warnings

import numpy as np
from PIL import Image, UnidentifiedImageError

from service.problems import ProblemError

IMAGE_FORMATS = {"PNG": "image/png", "JPEG": "image/jpeg", "WEBP": "image/webp"}
"""Accepted upload formats (Pillow format name -> media type)."""


def set_pixel_limit(max_pixels: int) -> None:
    """Install the service's cap as Pillow's decompression-bomb limit (process-wide)."""
    Image.MAX_IMAGE_PIXELS = int(max_pixels)


def decode_image(data: bytes, *, max_pixels: int, name: str = "image") -> np.ndarray:
    """An uploaded PNG, JPEG or WebP as straight-alpha RGBA floats ``[H, W, 4]`` in [0, 1]
    (alpha 1 where the file has none).

    Raises ``ProblemError``: 415 for anything that is not one of those formats, 413 for more than
    ``max_pixels`` pixels, 422 for a truncated or corrupt file.
    """
    accepted = ", ".join(IMAGE_FORMATS.values())
    if not data:
        raise ProblemError(422, "Empty image", f"{name} is empty; upload a PNG, JPEG or WebP file", kind="bad-image")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data), formats=list(IMAGE_FORMATS))
            width, height = image.size
            if width * height > max_pixels:
                raise Image.DecompressionBombError(f"{width}x{height}")
            image.load()
    except UnidentifiedImageError:
        raise ProblemError(415, "Unsupported image type", f"{name} is not an image this service reads; send one of {accepted}",
                           kind="unsupported-media-type") from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise ProblemError(413, "Image too large", f"{name} has more than {max_pixels} pixels; downscale it "
                           "(the limit is HYPNERF_LIMITS__MAX_IMAGE_PIXELS)", kind="image-too-large") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise ProblemError(422, "Corrupt image", f"{name} could not be decoded ({exc}); send a complete PNG, JPEG or WebP file",
                           kind="bad-image") from None
    rgba = np.asarray(image.convert("RGBA"), dtype=np.float32) / 255.0
    return rgba
