"""Configs as dataclasses, written to and read from JSON by one pair of functions.

:func:`to_dict` turns a (nested) config dataclass into plain JSON values; :func:`from_dict`
rebuilds it from the field types: nested dataclasses recurse, tuples come back as tuples,
``X | None`` accepts null, and a polymorphic field (annotated with a type registered through
:func:`register_decoder`, such as the field protocol) is decoded by its registered function.
A class with a ``kind`` class variable writes it, so polymorphic configs say what they are.
Unknown keys are an error naming them, so a typo in a config file does not pass silently.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable
from typing import Any

_DECODERS: dict[Any, Callable[[dict], Any]] = {}


def register_decoder(annotation: Any, decode: Callable[[dict], Any]) -> None:
    """Decode values of fields annotated ``annotation`` with ``decode(json_value)``."""
    _DECODERS[annotation] = decode


def to_dict(config: Any) -> dict:
    """A config dataclass as a JSON-ready dict (``kind`` first when the class has one)."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError(f"to_dict takes a dataclass instance, got {type(config).__name__}")
    out: dict[str, Any] = {}
    kind = getattr(type(config), "kind", None)
    if isinstance(kind, str):
        out["kind"] = kind
    for item in dataclasses.fields(config):
        out[item.name] = _encode(getattr(config, item.name))
    return out


def _encode(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_dict(value)
    if isinstance(value, (tuple, list)):
        return [_encode(v) for v in value]
    if isinstance(value, dict):
        return {k: _encode(v) for k, v in value.items()}
    return value


def from_dict(cls: type, data: dict) -> Any:
    """Rebuild ``cls`` from what :func:`to_dict` wrote; missing keys take the defaults."""
    if not isinstance(data, dict):
        raise ValueError(f"a {cls.__name__} must be a JSON object, got {type(data).__name__}")
    names = {item.name for item in dataclasses.fields(cls) if item.init}
    unknown = sorted(set(data) - names - {"kind"})
    if unknown:
        raise ValueError(f"unknown {cls.__name__} settings {unknown}; known: {sorted(names)}")
    kind = getattr(cls, "kind", None)
    if isinstance(kind, str) and data.get("kind", kind) != kind:
        raise ValueError(f"a {cls.__name__} has kind {kind!r}, got {data['kind']!r}")
    hints = typing.get_type_hints(cls)
    return cls(**{name: _decode(hints[name], value) for name, value in data.items() if name in names})


def _decode(annotation: Any, value: Any) -> Any:
    if annotation in _DECODERS:
        return _DECODERS[annotation](value)
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        options = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _decode(options[0], value) if len(options) == 1 else value
    if origin is tuple:
        args = typing.get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_decode(args[0], v) for v in value)
        return tuple(_decode(a, v) for a, v in zip(args, value)) if args else tuple(value)
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
        return from_dict(annotation, value)
    if annotation is float and isinstance(value, int):
        return float(value)
    return value
