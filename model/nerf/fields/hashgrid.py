"""The NeRF field: a hash encoding plus two small bias-free MLPs, with weights supplied per object.

The field is functional: every weight is an argument (a ``FieldParams`` dict of tensors with a
leading object dimension ``B``), because the hypernetwork emits them. Layout, as in the official
HyP-NeRF code (an InstantNGP instantiation):

* density net: ``L*F -> hidden -> 1 + geo_features``; density through a truncated exponential;
* colour net: ``SH(dir, degree 4) + geo_features -> hidden -> hidden -> 3``, sigmoid.

Layers are bias-free, so the emitted tensors are the hash tables and five weight matrices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import torch

from model.nerf.encodings.hashgrid import HashGridConfig, encode, init_tables
from model.nerf.encodings.sh import sh_encode
from model.nerf.fields.protocol import FieldParams


# Largest pre-activation the density exponential sees: exp(15) ~ 3.3e6, far above any density a
# fitted object needs, and small enough that sigma * step stays finite in float16.
_MAX_LOG_DENSITY = 15.0


class _TruncatedExp(torch.autograd.Function):
    """exp with its input clamped at ``_MAX_LOG_DENSITY``; the gradient uses the same clamp so it
    keeps flowing (as torch-ngp's trunc_exp) instead of vanishing above the clamp."""

    @staticmethod
    def forward(ctx, x):
        out = torch.exp(x.clamp(max=_MAX_LOG_DENSITY))
        ctx.save_for_backward(out)
        return out

    @staticmethod
    def backward(ctx, grad):
        (out,) = ctx.saved_tensors
        return grad * out


def truncated_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncatedExp.apply(x)


@dataclass
class FieldConfig:
    """The hash-grid field (MRHE + small MLPs).

    Implements the field protocol (``model.nerf.fields.protocol.Field``), which the renderer, the
    fits and the hypernetwork use.
    """

    kind: ClassVar[str] = "hashgrid"

    encoding: HashGridConfig = field(default_factory=HashGridConfig)
    hidden: int = 64
    geo_features: int = 15
    color_hidden: int = 64
    sh_degree: int = 4

    @property
    def color_input(self) -> int:
        return self.sh_degree**2 + self.geo_features

    def weight_shapes(self) -> dict[str, tuple[int, int]]:
        """Shapes (in, out) of the five bias-free weight matrices, in emission order."""
        return {
            "density0": (self.encoding.output_dim, self.hidden),
            "density1": (self.hidden, 1 + self.geo_features),
            "color0": (self.color_input, self.color_hidden),
            "color1": (self.color_hidden, self.color_hidden),
            "color2": (self.color_hidden, 3),
        }

    def param_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-object shape of every emitted tensor (no batch dimension), in emission order."""
        return {"tables": tuple(self.encoding.table_shape), **self.weight_shapes()}

    def shape_param_names(self) -> list[str]:
        """Tensors that hold geometry (the hypernetwork drives them from the shape code)."""
        return ["tables", "density0", "density1"]

    def color_param_names(self) -> list[str]:
        """Tensors that hold appearance (driven by the colour code)."""
        return ["color0", "color1", "color2"]

    def param_count(self) -> int:
        return sum(math.prod(shape) for shape in self.param_shapes().values())

    def init_params(self, batch: int = 1, *, generator=None, device=None) -> FieldParams:
        return init_params(self, batch, generator=generator, device=device)

    def density(self, params: FieldParams, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return density(params, points, self)

    def view_term(self, params: FieldParams, directions: torch.Tensor) -> torch.Tensor:
        return view_term(params, directions, self)

    def color_from_view_term(self, params: FieldParams, geo: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        return color_from_view_term(params, geo, view, self)


def init_params(cfg: FieldConfig, batch: int = 1, *, generator=None, device=None) -> FieldParams:
    """Fresh per-object parameters: tiny uniform tables and Kaiming-uniform weights."""
    params = {"tables": init_tables(cfg.encoding, batch, generator=generator, device=device)}
    for name, (fan_in, fan_out) in cfg.weight_shapes().items():
        bound = math.sqrt(6.0 / fan_in)
        w = torch.rand(batch, fan_in, fan_out, generator=generator, device=device) * 2 - 1
        params[name] = w * bound
    return params


def validate_params(cfg: FieldConfig, params: FieldParams) -> int:
    """Check names and shapes against the config; return the object count ``B``."""
    expected = cfg.param_shapes()
    if set(params) != set(expected):
        raise ValueError(f"field parameters must be exactly {sorted(expected)}, got {sorted(params)}")
    batch = params["tables"].shape[0]
    for name, shape in expected.items():
        if tuple(params[name].shape[1:]) != tuple(shape) or params[name].shape[0] != batch:
            raise ValueError(f"field parameter {name!r} has shape {tuple(params[name].shape)}, expected ({batch}, {shape})")
    return batch


def select(params: FieldParams, index: int) -> FieldParams:
    """The parameters of one object, keeping a batch dimension of 1."""
    return {k: v[index : index + 1] for k, v in params.items()}


def density(params: FieldParams, points: torch.Tensor, cfg: FieldConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Density ``[B, N]`` and geometry features ``[B, N, geo]`` at ``points [B, N, 3]`` in [0,1]^3."""
    feats = encode(points, params["tables"], cfg.encoding)
    hidden = torch.relu(feats @ params["density0"])
    out = hidden @ params["density1"]
    # the exponential in float32: under float16 autocast exp(log-density > 11.1) would overflow
    return truncated_exp(out[..., 0].float()), out[..., 1:]


def view_term(params: FieldParams, directions: torch.Tensor, cfg: FieldConfig) -> torch.Tensor:
    """The view-direction part of the colour net's first layer, ``[B, R, color_hidden]``.

    The first layer is linear in its concatenated input, so the SH part can be computed once per
    ray and shared by all samples of that ray instead of encoding the direction per sample.
    """
    sh = sh_encode(directions, cfg.sh_degree)
    return sh.to(params["color0"].dtype) @ params["color0"][:, : sh.shape[-1]]


def color_from_view_term(params: FieldParams, geo: torch.Tensor, view: torch.Tensor, cfg: FieldConfig) -> torch.Tensor:
    """RGB in [0,1] ``[B, N, 3]`` from geometry features and each sample's ``view_term`` row."""
    x = torch.relu(geo @ params["color0"][:, cfg.sh_degree**2 :] + view)
    x = torch.relu(x @ params["color1"])
    return torch.sigmoid(x @ params["color2"])


def color(params: FieldParams, geo: torch.Tensor, directions: torch.Tensor, cfg: FieldConfig) -> torch.Tensor:
    """RGB in [0,1] ``[B, N, 3]`` from geometry features and unit view directions ``[B, N, 3]``."""
    return color_from_view_term(params, geo, view_term(params, directions, cfg), cfg)
