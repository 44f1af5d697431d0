"""Shape augmentation: more training shapes from a category's own meshes by smooth deformations.

A category prior with few shapes generalises as far as its shapes reach; each augmented copy of
a mesh is a new shape (its own shape code) made by

- anisotropic scaling of width (x), depth (y) and height (z),
- a piecewise-linear stretch of the height about a cut, so the part below it (legs, seat base)
  and the part above it (back, armrests) grow or shrink by different factors, continuously,
- mirroring across the left-right plane (x), which keeps the mesh outward-facing.

The maps are continuous on the mesh, so connectivity, materials and UVs are kept as they are.
Copies of a mesh share its split (they are grouped under the source id), and only meshes of the
train split are augmented, so no test shape, nor a deformation of one, is ever trained on.
Everything is seeded by a stable hash of the copy's id.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from model.data.meshes import RenderMesh
from model.data.variants import stable_seed


@dataclass(frozen=True)
class AugmentRanges:
    """Ranges the deformations are drawn from (uniformly; the cut as a fraction of the height)."""

    scale: tuple[float, float] = (0.75, 1.3)
    stretch: tuple[float, float] = (0.7, 1.45)
    cut: tuple[float, float] = (0.3, 0.6)
    mirror_probability: float = 0.5


@dataclass(frozen=True)
class Deformation:
    """One drawn augmentation: axis scales, the height cut (fraction), the stretches below and above it."""

    scale: tuple[float, float, float]
    cut: float
    lower: float
    upper: float
    mirror: bool

    def to_json(self) -> dict:
        return asdict(self)


def draw_deformation(key: str, ranges: AugmentRanges = AugmentRanges()) -> Deformation:
    """The deformation of the copy named ``key`` (the same in every process)."""
    rng = np.random.default_rng(stable_seed(key))
    scale = tuple(float(s) for s in rng.uniform(*ranges.scale, size=3))
    return Deformation(
        scale=scale,  # type: ignore[arg-type]
        cut=float(rng.uniform(*ranges.cut)),
        lower=float(rng.uniform(*ranges.stretch)),
        upper=float(rng.uniform(*ranges.stretch)),
        mirror=bool(rng.uniform() < ranges.mirror_probability),
    )


def height_stretch(z: np.ndarray, cut: float, lower: float, upper: float) -> np.ndarray:
    """Heights ``[N]`` stretched by ``lower`` below ``cut`` (a height) and ``upper`` above it,
    continuous at the cut and fixed at the cut itself."""
    return np.where(z < cut, cut + (z - cut) * lower, cut + (z - cut) * upper)


def deformed(mesh: RenderMesh, deformation: Deformation) -> RenderMesh:
    """``mesh`` under ``deformation`` (position and overall size are normalised later)."""
    lo, hi = mesh.bounds()
    cut = lo[2] + deformation.cut * (hi[2] - lo[2])
    vertices = mesh.vertices.copy()
    vertices[:, 2] = height_stretch(vertices[:, 2], cut, deformation.lower, deformation.upper)
    sx, sy, sz = deformation.scale
    matrix = np.diag([-sx if deformation.mirror else sx, sy, sz])
    centre = 0.5 * (lo + hi)
    return replace(mesh, vertices=vertices - centre).transformed(matrix)
