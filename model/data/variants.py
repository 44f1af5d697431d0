"""Colour/material variants of a mesh: the same geometry painted differently.

A category prior learns shape and colour as separate codes; variants of one mesh give it many
instances that share a shape and differ only in colour, which is what disentanglement needs.
Variant 0 is the mesh as it is. Every other variant gives each material a colour from the palette
(distinct colours for distinct materials while the palette lasts), jittered in HSV (Python's
``colorsys``) so variants of one hue are not identical. Textures keep their pattern: a texture
becomes its luminance, scaled so its bright end is 1, and the material colour is raised to keep
the mean albedo at the chosen colour. Corner (vertex) colours keep their luminance and lose their
hue, so the material colour decides it. Everything is seeded by a stable hash of the object id.
"""

from __future__ import annotations

import colorsys
import hashlib
from dataclasses import replace

import numpy as np

from model.data.colours import PALETTE
from model.data.meshes import Material, RenderMesh

# Rec. 709 luma weights: how bright each sRGB channel looks.
_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def stable_seed(key: str) -> int:
    """A seed from a string that is the same in every process (unlike ``hash``)."""
    return int.from_bytes(hashlib.sha256(key.encode("utf-8")).digest()[:8], "little")


def jittered(colour: tuple[float, float, float], rng: np.random.Generator) -> np.ndarray:
    """A palette colour with small random shifts of hue, saturation and value."""
    h, s, v = colorsys.rgb_to_hsv(*colour)
    h = (h + rng.uniform(-0.03, 0.03)) % 1.0
    s = float(np.clip(s * rng.uniform(0.85, 1.1), 0.0, 1.0))
    v = float(np.clip(v * rng.uniform(0.85, 1.1), 0.05, 1.0))
    return np.array(colorsys.hsv_to_rgb(h, s, v), dtype=np.float32)


def luminance_pattern(texture: np.ndarray) -> np.ndarray:
    """A texture ``[H, W, 4]`` as grey RGBA whose 99th-percentile luminance is 1."""
    luma = texture[..., :3] @ _LUMA
    top = max(float(np.percentile(luma, 99)), 1e-3)
    grey = np.clip(luma / top, 0.0, 1.0)
    return np.concatenate([np.repeat(grey[..., None], 3, axis=-1), texture[..., 3:]], axis=-1).astype(np.float32)


def recoloured(material: Material, colour: np.ndarray) -> Material:
    """``material`` with base colour ``colour`` (sRGB) and, if textured, its texture's pattern only."""
    if material.texture is None:
        return Material(material.name, np.append(colour, material.colour[3]).astype(np.float32))
    pattern = luminance_pattern(material.texture)
    mean = max(float(pattern[..., 0].mean()), 1e-3)
    base = np.clip(colour / mean, 0.0, 1.0)
    return Material(material.name, np.append(base, material.colour[3]).astype(np.float32), pattern)


def material_variants(mesh: RenderMesh, count: int, seed: str) -> list[RenderMesh]:
    """``count`` paintings of ``mesh``: the original, then ``count - 1`` recoloured ones."""
    if count < 1:
        raise ValueError(f"the number of variants must be at least 1, got {count}")
    rng = np.random.default_rng(stable_seed(seed))
    names = list(PALETTE)
    grey_corners = np.concatenate(
        [np.repeat((mesh.corner_colour[..., :3] @ _LUMA)[..., None], 3, axis=-1), mesh.corner_colour[..., 3:]], axis=-1
    ).astype(np.float32)
    variants = [mesh]
    for _ in range(1, count):
        order = rng.permutation(len(names))
        materials = [
            recoloured(material, jittered(PALETTE[names[order[i % len(names)]]], rng)) for i, material in enumerate(mesh.materials)
        ]
        variants.append(replace(mesh, materials=materials, corner_colour=grey_corners))
    return variants
