"""Config sections read once into typed, frozen dataclasses (:func:`read_section`).

Reading is strict: an ``int`` takes integers only (``32.0``, ``true``, ``"32"`` refused), a
``float`` any real but a boolean; unknown keys are refused; a dataclass checks its ranges in
``__post_init__`` with :class:`SettingError`. The ``require_*`` checks apply the same rules to
a value a network part reads itself (``conf/model``).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar, Union

from omegaconf import DictConfig, OmegaConf

__all__ = [
    "ConfigTree",
    "SettingError",
    "as_dict",
    "at_least",
    "lookup",
    "positive",
    "read_section",
    "require_int",
    "require_nonnegative",
    "require_switch",
    "unit_interval",
]

T = TypeVar("T")

#: A config as a plain tree of dicts and lists, interpolations resolved (:func:`as_dict`).
ConfigTree = Mapping[str, Any]


def lookup(tree: ConfigTree, key: str) -> tuple[bool, Any]:
    """``(found, value)`` of the dotted ``key`` in ``tree``."""
    node: Any = tree
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False, None
        node = node[part]
    return True, node


class SettingError(ValueError):
    """A value out of its range, raised by a section's ``__post_init__`` for one field."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field} {message}")
        self.field, self.message = field, message


def as_dict(node: Any) -> dict[str, Any]:
    """``node`` (a config or plain mapping) resolved into a plain ``dict``; else a TypeError."""
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, dict):
        raise TypeError(f"expected a config mapping, got {type(node).__name__}: {node!r}")
    return node


def unit_interval(name: str, value: float) -> None:
    """Raise :class:`SettingError` unless ``value`` lies in [0, 1]."""
    if not 0.0 <= value <= 1.0:
        raise SettingError(name, f"must lie in [0, 1], got {value}")


def positive(name: str, value: float, strict: bool = True) -> None:
    """Raise :class:`SettingError` unless ``value`` is finite and > 0 (>= 0: ``strict=False``)."""
    ok = math.isfinite(value) and (value > 0 if strict else value >= 0)
    if not ok:
        raise SettingError(
            name, f"must be a finite number {'>' if strict else '>='} 0, got {value}"
        )


def _integer_at_least(low: int) -> str:
    """What an integer setting must be: ``a positive integer`` for ``low`` 1, ..."""
    return {0: "a non-negative integer", 1: "a positive integer"}.get(low, f"an integer >= {low}")


def at_least(low: int, section: Any, *names: str) -> None:
    """Raise :class:`SettingError` for the first of ``section``'s ``names`` below ``low``."""
    for name in names:
        value = getattr(section, name)
        if value is not None and value < low:
            raise SettingError(name, f"must be {_integer_at_least(low)}, got {value}")


def _kind(value: Any) -> str:
    """``value`` and its type, for an error message."""
    return f"{value!r} ({type(value).__name__})"


#: What a scalar setting must be, and the test of a value.
_SCALARS: dict[Any, tuple[str, Any]] = {
    bool: ("true or false", lambda v: isinstance(v, bool)),
    int: ("an integer", lambda v: not isinstance(v, bool) and isinstance(v, numbers.Integral)),
    float: ("a number", lambda v: not isinstance(v, bool) and isinstance(v, numbers.Real)),
    str: ("a string", lambda v: isinstance(v, str)),
}


def require_int(key: str, value: Any, minimum: int = 1) -> int:
    """``value`` as an ``int`` if it is an integer ``>= minimum``; else a ``ValueError``.

    >>> require_int("model.hidden", 32.9)
    Traceback (most recent call last):
    ...
    ValueError: model.hidden must be an integer, got 32.9 (float)
    """
    if not _SCALARS[int][1](value):
        raise ValueError(f"{key} must be an integer, got {_kind(value)}")
    if value < minimum:
        raise ValueError(f"{key} must be {_integer_at_least(minimum)}, got {value}")
    return int(value)


def require_switch(key: str, value: Any) -> int:
    """``value`` as 0 or 1 if it is a boolean or the integer 0 or 1; else a ``ValueError``."""
    if isinstance(value, numbers.Integral) and value in (0, 1):
        return int(value)
    raise ValueError(f"{key} must be 0 or 1 (false/true), got {_kind(value)}")


def require_nonnegative(key: str, value: Any) -> float:
    """``value`` as a ``float`` if it is a finite real number ``>= 0``; else a ``ValueError``."""
    if not (_SCALARS[float][1](value) and math.isfinite(value) and value >= 0.0):
        raise ValueError(f"{key} must be a finite number >= 0, got {_kind(value)}")
    return float(value)


def _convert(kind: Any, value: Any, key: str) -> Any:
    """``value`` as ``kind`` (a type annotation), strictly; else a ValueError naming ``key``."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            return _convert(inner[0], value, key)
        raise TypeError(f"{key}: unions of several types are not supported")
    if value is None:
        raise ValueError(f"{key} must be set (null is not allowed here)")
    if origin is tuple:
        if isinstance(value, str | bytes) or not isinstance(value, list | tuple):
            raise ValueError(f"{key} must be a list, got {_kind(value)}")
        return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(kind):
        return read_section(kind, value, key)  # type: ignore[arg-type]
    if kind in _SCALARS:
        what, ok = _SCALARS[kind]
        if not ok(value):
            raise ValueError(f"{key} must be {what}, got {_kind(value)}")
        return kind(value)
    if kind is Any:
        return value
    raise TypeError(f"{key}: unsupported setting type {kind!r}")


def read_section(cls: type[T], node: Any, key: str) -> T:
    """The dataclass ``cls`` read from the mapping ``node`` (config section ``key``).

    Raises
    ------
    ValueError
        Naming the key: an unknown or missing key, a value of another type, or one that
        ``cls`` refuses (:class:`SettingError`).
    """
    if node is None:
        node = {}
    if not isinstance(node, Mapping):
        raise ValueError(f"{key} must be a mapping of settings, got {_kind(node)}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(map(str, node)) - set(fields))
    if unknown:
        raise ValueError(f"{key} has unknown keys {unknown}; it takes {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for name, field in fields.items():
        if name in node:
            values[name] = _convert(hints[name], node[name], f"{key}.{name}")
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ValueError(f"{key}.{name} must be set")
    try:
        return cls(**values)
    except SettingError as exc:
        raise ValueError(f"{key}.{exc.field} {exc.message}") from None
