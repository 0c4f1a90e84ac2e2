"""Round-trip frozen configuration dataclasses through plain dicts (and so JSON).

Configs are stored in the map's meta record, so a map remembers how it was built. Unknown keys are
refused (a typo must not silently fall back to a default); missing keys take the defaults, which
lets a newer library open a map whose config predates a field.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

from sprint_map.errors import ConfigError

T = TypeVar("T")


def to_dict(obj: Any) -> dict[str, Any]:
    """Return a JSON-ready dict of a (possibly nested) config dataclass."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
    """Build config dataclass ``cls`` from ``data``, recursing into nested configs.

    Raises
    ------
    ConfigError
        On a key ``cls`` does not have, or a value its ``__post_init__`` refuses.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{cls.__name__}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{cls.__name__}: unknown option(s) {', '.join(unknown)}")
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        hint = hints.get(name)
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            value = from_dict(hint, value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{cls.__name__}: {exc}") from exc


def replace(obj: T, **changes: Any) -> T:
    """Return a copy of config ``obj`` with ``changes``, validated like :func:`from_dict`."""
    data = to_dict(obj)
    data.update(changes)
    return from_dict(type(obj), data)
