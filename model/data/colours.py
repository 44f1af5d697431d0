"""Named colours: the palette procedural objects are painted with, and naming a mesh's main colour for captions.

Names are matched in CIELAB (via **scikit-image**'s ``rgb2lab``), where distances follow
perceived differences far better than in RGB, so dark browns are not called black.
"""

from __future__ import annotations

import numpy as np
from skimage.color import rgb2lab

from model.data.meshes import RenderMesh

# sRGB in [0, 1].
PALETTE = {
    "red": (0.80, 0.15, 0.12),
    "orange": (0.92, 0.50, 0.10),
    "yellow": (0.93, 0.80, 0.18),
    "green": (0.20, 0.58, 0.25),
    "teal": (0.10, 0.55, 0.55),
    "blue": (0.15, 0.30, 0.75),
    "purple": (0.50, 0.25, 0.65),
    "pink": (0.92, 0.55, 0.68),
    "brown": (0.50, 0.32, 0.18),
    "beige": (0.85, 0.76, 0.60),
    "black": (0.08, 0.08, 0.08),
    "white": (0.92, 0.92, 0.90),
    "grey": (0.50, 0.50, 0.50),
}

_NAMES = list(PALETTE)
_PALETTE_LAB = rgb2lab(np.array([PALETTE[n] for n in _NAMES])[None])[0]


def colour_names(rgb: np.ndarray) -> list[str]:
    """The nearest palette name of each sRGB colour ``[N, 3]`` in [0, 1]."""
    lab = rgb2lab(np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0)[None])[0]
    distance = np.linalg.norm(lab[:, None, :] - _PALETTE_LAB[None], axis=-1)
    return [_NAMES[i] for i in distance.argmin(axis=1)]


def largest_share(shares: dict[str, float]) -> str:
    """The name with the largest share; a tie goes to the name first in alphabetical order."""
    return max(sorted(shares), key=shares.get)


def dominant_colour(mesh: RenderMesh) -> str:
    """The palette name covering the largest surface area of the mesh (by mean face colour)."""
    triangles = mesh.triangles
    area = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    unique, inverse = np.unique(mesh.mean_face_colours()[:, :3], axis=0, return_inverse=True)
    names = np.array(colour_names(unique / 255.0))[inverse.reshape(-1)]
    totals = {name: float(area[names == name].sum()) for name in set(names.tolist())}
    return largest_share(totals)


def article(word: str) -> str:
    return "an" if word[:1].lower() in "aeiou" else "a"


def default_caption(mesh: RenderMesh, noun: str) -> str:
    """``a <main colour> <noun>``, e.g. "a brown armchair"."""
    colour = dominant_colour(mesh)
    return f"{article(colour)} {colour} {noun.lower()}"
