"""NeRF fields: the protocol (``protocol``) and its two kinds, by the ``kind`` their configs write.

``hashgrid`` (``hashgrid.FieldConfig``) is the InstantNGP-style field HyP-NeRF predicts;
``positional`` (``positional.PEFieldConfig``) is the original NeRF's positional-encoding MLP, kept
for the ablation without MRHE. Configs annotated with :class:`Field` decode to the right kind.
"""

from __future__ import annotations

import torch

from model.nerf import config
from model.nerf.fields.hashgrid import FieldConfig
from model.nerf.fields.positional import PEFieldConfig
from model.nerf.fields.protocol import Field, FieldParams
from model.nerf.scene import SceneBox

KINDS: dict[str, type] = {FieldConfig.kind: FieldConfig, PEFieldConfig.kind: PEFieldConfig}


def field_config_from_dict(data: dict) -> Field:
    """The field config ``config.to_dict`` wrote; configs without a ``kind`` are hash-grid fields."""
    kind = data.get("kind", FieldConfig.kind)
    if kind not in KINDS:
        raise ValueError(f"unknown field kind {kind!r}; expected one of {sorted(KINDS)}")
    return config.from_dict(KINDS[kind], data)


config.register_decoder(Field, field_config_from_dict)


def world_density(params: FieldParams, field_cfg: Field, scene: SceneBox):
    """``fn(points [N, 3] world) -> density [N]`` of one object (batch 1), for grids and meshes."""

    def fn(points: torch.Tensor) -> torch.Tensor:
        return field_cfg.density(params, scene.to_unit(points)[None])[0][0]

    return fn


def world_color(params: FieldParams, field_cfg: Field, scene: SceneBox, view_direction=(0.0, 0.0, -1.0)):
    """``fn(points [N, 3] world) -> RGB [N, 3]`` seen along one direction (straight down by default:
    the field's view dependence is weak), for vertex colours."""

    def fn(points: torch.Tensor) -> torch.Tensor:
        _, geo = field_cfg.density(params, scene.to_unit(points)[None])
        direction = torch.tensor(view_direction, device=points.device).expand_as(points)[None]
        return field_cfg.color_from_view_term(params, geo, field_cfg.view_term(params, direction))[0]

    return fn

__all__ = ["KINDS", "Field", "FieldConfig", "FieldParams", "PEFieldConfig", "field_config_from_dict", "world_color", "world_density"]
