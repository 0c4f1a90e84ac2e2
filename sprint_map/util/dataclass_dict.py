"""Round-trip frozen configuration dataclasses through plain dicts (and so JSON).

Configs are stored in the map's meta record, so a map remembers how it was built. Unknown keys are
refused (a typo must not silently fall back to a default); missing keys take the defaults, which
lets a newer library open a map whose config predates a field.

Every value is checked against its field's type before the dataclass sees it (its
``__post_init__`` keeps the range checks): ``int`` takes integers only (not ``1.5``, not ``True``),
``float`` any real number (stored as a float), ``bool`` only ``true``/``false``, ``str`` only
text, ``X | None``, ``tuple[X, ...]``, ``tuple[X, Y]``, ``dict[str, ...]``, ``Literal[...]``
and nested config dataclasses as such. A refused value is one :class:`ConfigError` line naming
the key (``MapConfig.hmm: k must be an integer, got 1.5``).

The range checks of the ``__post_init__`` methods use the two rules here, :func:`check_int` and
:func:`check_number`, so that every config says a bound the same way (a ValueError, which
:func:`from_dict` turns into a ConfigError naming the config).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

from sprint_map.errors import ConfigError

__all__ = ["check_int", "check_number", "from_dict", "replace", "to_dict"]

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


def from_dict(cls: type[T], data: Mapping[str, Any], *, where: str | None = None) -> T:
    """Build config dataclass ``cls`` from ``data``, recursing into nested configs.

    ``where`` names ``cls`` in messages (default its class name; nested: ``MapConfig.hmm``).

    Raises
    ------
    ConfigError
        On a key ``cls`` does not have, a value not of its field's type, or a value its
        ``__post_init__`` refuses.
    """
    where = where or cls.__name__
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(str(key) for key in set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown option(s) {', '.join(unknown)}",
                          unknown=tuple(f"{where}.{key}" for key in unknown))
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints.get(name, Any), value, name, where)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


class _Refused(Exception):
    """A value is not of its type: ``str(exc)`` says what the type wants."""


def _coerce(hint: Any, value: Any, name: str, where: str) -> Any:
    """``value`` as field ``name`` of type ``hint`` holds it, or ConfigError naming the key."""
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if isinstance(value, hint):
            return value
        return from_dict(hint, value, where=f"{where}.{name}")
    try:
        return _convert(hint, value)
    except _Refused as exc:
        shown = repr(value)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise ConfigError(f"{where}: {name} must be {exc}, got {shown}") from None


def _convert(hint: Any, value: Any) -> Any:
    """``value`` checked against (and normalised to) ``hint``; raises :class:`_Refused`."""
    if hint is Any or isinstance(hint, typing.TypeVar):
        return value
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        for option in options:
            try:
                return _convert(option, value)
            except _Refused:
                continue
        wanted = " or ".join(_describe(a) for a in args)
        raise _Refused(wanted)
    if origin is typing.Literal:
        if any(value == a and type(value) is type(a) for a in args):
            return value
        raise _Refused("one of " + ", ".join(repr(a) for a in args))
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise _Refused(_describe(hint))
        try:
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(_convert(args[0], item) for item in value)
            if not args:
                return tuple(value)
            if len(value) != len(args):
                raise _Refused(_describe(hint))
            return tuple(_convert(a, item) for a, item in zip(args, value, strict=True))
        except _Refused:
            raise _Refused(_describe(hint)) from None
    if origin is dict or hint is dict:
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            raise _Refused("an object with text keys")
        return dict(value)
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise _Refused("true or false")
    if hint is int:
        if isinstance(value, numbers.Integral) and not isinstance(value, bool):
            return int(value)
        raise _Refused("an integer")
    if hint is float:
        if isinstance(value, numbers.Real) and not isinstance(value, bool):
            return float(value)
        raise _Refused("a number")
    if hint is str:
        if isinstance(value, str):
            return value
        raise _Refused("text")
    if isinstance(value, list):  # a type this module does not check: as before
        return tuple(value)
    return value


def _describe(hint: Any) -> str:
    """How a message names what ``hint`` wants."""
    if hint is type(None):
        return "null"
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_describe(args[0]).removeprefix('a ').removeprefix('an ')}s"
        return f"a list of {len(args)} values"
    names = {bool: "true or false", int: "an integer", float: "a number", str: "text"}
    return names.get(hint, getattr(hint, "__name__", str(hint)))


def replace(obj: T, **changes: Any) -> T:
    """Return a copy of config ``obj`` with ``changes``, validated like :func:`from_dict`."""
    data = to_dict(obj)
    data.update(changes)
    return from_dict(type(obj), data)


def check_int(name: str, value: Any, lo: int) -> None:
    """Raise ValueError (``{name} must be an integer >= {lo}``) unless ``value`` is an integer
    (not a bool) of at least ``lo``. O(1)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ValueError(f"{name} must be an integer >= {lo}")


def check_number(name: str, value: Any, lo: float, hi: float, *, lo_open: bool = False,
                 hi_open: bool = False) -> None:
    """Raise ValueError unless ``value`` is a finite real number (not a bool) in the range
    ``[lo, hi]`` (``(`` / ``)`` where ``lo_open`` / ``hi_open``). O(1)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number")
    if value < lo or (lo_open and value == lo) or value > hi or (hi_open and value == hi):
        left = "(" if lo_open else "["
        right = ")" if hi_open else "]"
        raise ValueError(f"{name} must be in {left}{lo}, {hi}{right}")
