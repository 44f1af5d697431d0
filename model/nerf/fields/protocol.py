"""What every NeRF field offers the renderer, the fits and the hypernetwork.

A field is a config object whose methods take the per-object weights as an argument
(``FieldParams``: a dict of tensors with a leading object dimension ``B``), because the
hypernetwork emits them. Points arrive in the unit cube of the scene box (``model.nerf.scene``).
"""

from __future__ import annotations

from typing import ClassVar, Protocol, runtime_checkable

import torch

FieldParams = dict[str, torch.Tensor]


@runtime_checkable
class Field(Protocol):
    kind: ClassVar[str]

    def param_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-object shape of every emitted tensor (no batch dimension), in emission order."""

    def shape_param_names(self) -> list[str]:
        """Tensors holding geometry (driven by the shape code)."""

    def color_param_names(self) -> list[str]:
        """Tensors holding appearance (driven by the colour code)."""

    def param_count(self) -> int: ...

    def init_params(self, batch: int = 1, *, generator=None, device=None) -> FieldParams:
        """Fresh weights for ``batch`` objects."""

    def density(self, params: FieldParams, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density ``[B, N]`` (per unit length of the unit cube) and geometry features ``[B, N, G]``
        at unit points ``[B, N, 3]``."""

    def view_term(self, params: FieldParams, directions: torch.Tensor) -> torch.Tensor:
        """Per-ray part of the colour net, ``[B, R, H]``, from unit directions ``[B, R, 3]``."""

    def color_from_view_term(self, params: FieldParams, geo: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 1] ``[B, N, 3]`` from geometry features and each sample's view-term row."""
