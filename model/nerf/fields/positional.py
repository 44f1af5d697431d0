"""The original NeRF field (positional encoding + a deep MLP), functional, for the ablation without MRHE.

What it is
    The field of Mildenhall et al. (NeRF, ECCV 2020): points are mapped to sinusoidal features
    ``[x, sin(2^k pi x), cos(2^k pi x)]`` for ``k < 10`` (directions with ``k < 4``), a ``depth``-layer
    ReLU trunk of ``width`` units (8 layers in NeRF) with a skip connection that concatenates the
    encoded input to the activation of trunk layer ``skip`` (0-based; NeRF's ``skips=[4]``: the fifth
    layer's activation, so ``trunk{skip+1}`` reads ``[PE(x), h]``), then a density head and a
    ``width -> width`` feature layer without activation; the colour net reads
    ``[feature, PE(dir)]`` through one ReLU layer of ``width // 2`` units and a sigmoid RGB layer.

Why it exists
    HyP-NeRF's Table 4 ablates the multi-resolution hash encoding (MRHE): the hypernetwork then
    predicts this field instead of the hash-grid one in ``model.nerf.fields.hashgrid``. Because the hypernetwork
    emits every weight, the field is functional exactly like ``model.nerf.fields.hashgrid.FieldConfig``: all
    weights are arguments (a dict of tensors with a leading object dimension ``B``) and the config
    implements the same field protocol (``model.nerf.fields.protocol.Field``), so the renderer,
    the fits and the hypernetwork take either kind.

Differences from NeRF's MLP
    * Layers are bias-free, as in the hash-grid field: the hypernetwork emits weight matrices only.
    * Density goes through the truncated exponential of ``model.nerf.fields.hashgrid`` (as the hash-grid field)
      instead of NeRF's ReLU, so both kinds of the ablation share the density parameterisation.
    * Points arrive in [0,1]^3 (the renderer's unit box) and are mapped to [-1,1]^3 before the
      encoding, so the lowest frequency ``sin(pi x)`` spans one period over the box.

Parameter matching
    The default ``width`` (86) is chosen so that ``PEFieldConfig().param_count()`` (75,078) is as
    close as possible to ``FieldConfig().param_count()`` (74,880: the hash-grid NeRF's tables plus
    its MLPs; 0.26% apart). The ablation thus compares fields with the same number of emitted
    parameters, and the hypernetwork's output layer has the same size for either kind. (NeRF itself
    uses ``width = 256``, about 0.6M parameters.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch

from model.nerf.encodings.positional import encoded_dim, positional_encoding
from model.nerf.fields.hashgrid import truncated_exp
from model.nerf.fields.protocol import FieldParams

# Scale of the Kaiming-uniform density column at initialisation (see ``PEFieldConfig.init_params``).
_DENSITY_INIT_SCALE = 0.25


def _compute_dtype(*tensors: torch.Tensor) -> torch.dtype:
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


@dataclass
class PEFieldConfig:
    """The positional-encoding NeRF field (no MRHE); same methods and semantics as ``FieldConfig``.

    ``skip`` is the 0-based trunk layer whose activation is concatenated with the encoded input
    (``None``: no skip); ``color_hidden`` defaults to ``width // 2``.
    """

    kind: ClassVar[str] = "positional"

    position_frequencies: int = 10
    direction_frequencies: int = 4
    depth: int = 8
    width: int = 86
    skip: int | None = 4
    color_hidden: int | None = None

    def __post_init__(self) -> None:
        if self.color_hidden is None:
            self.color_hidden = self.width // 2
        if self.depth < 1 or self.width < 1 or self.color_hidden < 1:
            raise ValueError(f"depth, width and color_hidden must be positive, got {self.depth}, {self.width}, {self.color_hidden}")
        if self.position_frequencies < 0 or self.direction_frequencies < 0:
            raise ValueError("frequency counts must be non-negative")
        if self.skip is not None and not 0 <= self.skip < self.depth - 1:
            raise ValueError(f"skip must be a trunk layer in [0, {self.depth - 2}] (or None), got {self.skip}")

    @property
    def position_dim(self) -> int:
        return encoded_dim(3, self.position_frequencies)

    @property
    def direction_dim(self) -> int:
        return encoded_dim(3, self.direction_frequencies)

    def param_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-object shape (in, out) of every emitted weight matrix (no batch dimension), in emission order."""
        shapes: dict[str, tuple[int, ...]] = {}
        for i in range(self.depth):
            fan_in = self.position_dim if i == 0 else self.width
            if self.skip is not None and i == self.skip + 1:
                fan_in += self.position_dim
            shapes[f"trunk{i}"] = (fan_in, self.width)
        shapes["density"] = (self.width, 1)
        shapes["feature"] = (self.width, self.width)
        shapes["color0"] = (self.width + self.direction_dim, self.color_hidden)
        shapes["color1"] = (self.color_hidden, 3)
        return shapes

    def shape_param_names(self) -> list[str]:
        """Tensors that hold geometry (the hypernetwork drives them from the shape code)."""
        return [f"trunk{i}" for i in range(self.depth)] + ["density", "feature"]

    def color_param_names(self) -> list[str]:
        """Tensors that hold appearance (driven by the colour code)."""
        return ["color0", "color1"]

    def param_count(self) -> int:
        return sum(math.prod(shape) for shape in self.param_shapes().values())

    def init_params(self, batch: int = 1, *, generator=None, device=None) -> FieldParams:
        """Fresh per-object weights, Kaiming-uniform (bound ``sqrt(6 / fan_in)``) like ``model.nerf.fields.hashgrid``."""
        params = {}
        for name, (fan_in, fan_out) in self.param_shapes().items():
            bound = math.sqrt(6.0 / fan_in)
            w = torch.rand(batch, fan_in, fan_out, generator=generator, device=device) * 2 - 1
            params[name] = w * bound
        # The density column: the trunk's ReLU activations are all non-negative with a mean of order
        # one, so a full-scale column gives log-densities spread over several units; a smaller
        # column keeps the initial density moderate (around 1 per unit length) everywhere.
        params["density"] = params["density"] * _DENSITY_INIT_SCALE
        return params

    def _encode_points(self, params: FieldParams, points: torch.Tensor) -> torch.Tensor:
        dtype = _compute_dtype(points, params["trunk0"])
        # nan_to_num then clamp, as the hash encoding: samples stay inside the unit box.
        x = torch.nan_to_num(points.to(dtype), nan=0.0).clamp(0.0, 1.0) * 2.0 - 1.0
        return positional_encoding(x, self.position_frequencies).to(params["trunk0"].dtype)

    def density(self, params: FieldParams, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density ``[B, N]`` and geometry features ``[B, N, width]`` at ``points [B, N, 3]`` in [0,1]^3.

        The features are NeRF's feature vector (the trunk output through the ``feature`` layer), so
        all geometry weights act here and the colour net reads only colour weights.
        """
        enc = self._encode_points(params, points)
        h = enc
        for i in range(self.depth):
            h = torch.relu(h @ params[f"trunk{i}"])
            if self.skip is not None and i == self.skip:
                h = torch.cat([enc.to(h.dtype), h], dim=-1)
        # the exponential in float32: under float16 autocast exp(log-density > 11) would overflow
        sigma = truncated_exp((h @ params["density"])[..., 0].float())
        return sigma, h @ params["feature"]

    def view_term(self, params: FieldParams, directions: torch.Tensor) -> torch.Tensor:
        """The view-direction part of the colour net's first layer, ``[B, R, color_hidden]``.

        The first colour layer is linear in ``[feature, PE(dir)]``, so the direction part is
        computed once per ray and shared by all samples of that ray.
        """
        dtype = _compute_dtype(directions, params["color0"])
        d = torch.nan_to_num(directions.to(dtype), nan=0.0)
        enc = positional_encoding(d, self.direction_frequencies).to(params["color0"].dtype)
        return enc @ params["color0"][:, self.width :]

    def color_from_view_term(self, params: FieldParams, geo: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """RGB in [0,1] ``[B, N, 3]`` from geometry features and each sample's ``view_term`` row."""
        x = torch.relu(geo @ params["color0"][:, : self.width] + view)
        return torch.sigmoid(x @ params["color1"])

    def color(self, params: FieldParams, geo: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """RGB in [0,1] ``[B, N, 3]`` from geometry features and unit view directions ``[B, N, 3]``."""
        return self.color_from_view_term(params, geo, self.view_term(params, directions))


