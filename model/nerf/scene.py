"""The scene box: the axis-aligned box a dataset's objects live in, and the map to unit coordinates.

Every part that needs a box (ray bounds, the field's encoding, occupancy grids, carving, meshes,
Chamfer units, the category data of a prior) takes a :class:`SceneBox`, which comes from the
dataset's ``aabb``; nothing else normalises coordinates by hand.

The field lives in the unit cube: a world point ``x`` is encoded at ``(x - min) / size`` in
[0, 1]^3, and densities are per unit of that cube's length. The renderer turns world step lengths
into unit ones with :meth:`SceneBox.unit_lengths`, so the same object written at any scale (box
and cameras scaled together) trains and renders the same field.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class SceneBox:
    """An axis-aligned box ``[min, max]`` in world coordinates (each a 3-tuple, ``min < max``)."""

    min: tuple[float, float, float] = (-0.5, -0.5, -0.5)
    max: tuple[float, float, float] = (0.5, 0.5, 0.5)

    def __post_init__(self):
        lo, hi = tuple(float(v) for v in self.min), tuple(float(v) for v in self.max)
        if len(lo) != 3 or len(hi) != 3:
            raise ValueError(f"a scene box needs 3 coordinates per corner, got {self.min} and {self.max}")
        if not all(math.isfinite(v) for v in lo + hi) or not all(a < b for a, b in zip(lo, hi)):
            raise ValueError(f"a scene box must be finite with min < max on every axis, got {lo} and {hi}")
        object.__setattr__(self, "min", lo)
        object.__setattr__(self, "max", hi)

    @classmethod
    def from_aabb(cls, aabb: Sequence[Sequence[float]] | torch.Tensor) -> SceneBox:
        """From ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` (a list, array or ``[2, 3]`` tensor)."""
        rows = torch.as_tensor(aabb, dtype=torch.float64).reshape(2, 3).tolist()
        return cls(tuple(rows[0]), tuple(rows[1]))

    @classmethod
    def cube(cls, half_side: float, center: Sequence[float] = (0.0, 0.0, 0.0)) -> SceneBox:
        return cls(tuple(c - half_side for c in center), tuple(c + half_side for c in center))

    def to_aabb(self) -> list[list[float]]:
        return [list(self.min), list(self.max)]

    def tensors(self, device=None, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        """``(min [3], max [3])`` as tensors on ``device``."""
        return torch.tensor(self.min, device=device, dtype=dtype), torch.tensor(self.max, device=device, dtype=dtype)

    @property
    def size(self) -> tuple[float, float, float]:
        return tuple(b - a for a, b in zip(self.min, self.max))

    @property
    def longest_side(self) -> float:
        """Length of the box's longest side: the world length of one unit of the field's cube."""
        return max(self.size)

    def to_unit(self, points: torch.Tensor) -> torch.Tensor:
        """World points ``[..., 3]`` -> unit coordinates in [0, 1]^3 (clamped onto the box)."""
        lo, hi = self.tensors(points.device, points.dtype)
        return ((points - lo) / (hi - lo)).clamp(0.0, 1.0)

    def from_unit(self, unit: torch.Tensor) -> torch.Tensor:
        """Unit coordinates ``[..., 3]`` -> world points."""
        lo, hi = self.tensors(unit.device, unit.dtype)
        return lo + unit * (hi - lo)

    def unit_lengths(self, directions: torch.Tensor) -> torch.Tensor:
        """Length in unit coordinates of one world unit travelled along each direction ``[..., 3]`` -> ``[...]``.

        A world step ``dt`` along a unit direction ``d`` covers ``dt * |d / size|`` of the unit cube,
        which is what a density per unit length multiplies.
        """
        lo, hi = self.tensors(directions.device, directions.dtype)
        return (directions / (hi - lo)).norm(dim=-1)


UNIT_BOX = SceneBox()
"""The box of this project's own datasets: [-0.5, 0.5]^3, objects with their longest side 0.9."""
