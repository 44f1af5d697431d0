"""The field kinds a NeRF can use, by the ``kind`` name their configs serialise with.

``hashgrid`` (``model.field``) is the InstantNGP-style field HyP-NeRF predicts; ``positional``
(``model.pe_field``) is the original NeRF's positional-encoding MLP, kept for the ablation
without MRHE. Both offer the same methods, so renderers, fits and the hypernetwork take either.
"""

from __future__ import annotations

from model.field import FieldConfig


def _kinds() -> dict[str, type]:
    from model.pe_field import PEFieldConfig

    return {FieldConfig.kind: FieldConfig, PEFieldConfig.kind: PEFieldConfig}


def field_config_from_dict(data: dict):
    """Build the field config a ``to_dict()`` wrote; configs without a ``kind`` are hash-grid fields."""
    kind = data.get("kind", FieldConfig.kind)
    kinds = _kinds()
    if kind not in kinds:
        raise ValueError(f"unknown field kind {kind!r}; expected one of {sorted(kinds)}")
    return kinds[kind].from_dict(data)
