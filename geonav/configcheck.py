"""Typed validation of config values read from TOML or JSON, in one place.

Every config of geonav is a frozen dataclass whose fields carry type hints
(``lr: float``, ``alts_m: tuple[float, ...]``, ``encoder_weights: str | None``).
:func:`build` checks a mapping against those hints before the dataclass is made,
so ``lr = "abc"`` in a TOML file is one :class:`~geonav.errors.ConfigError` that
names the table and the field, never a ``TypeError`` from a comparison in
``__post_init__``. Ranges and choices stay in each dataclass's ``__post_init__``.

Coercions are the lossless ones TOML and JSON need: an int where a float is
expected (``lr = 1``), a float with an integral value where an int is expected
(``episodes = 1e5``), a list where a tuple is expected.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Mapping
from typing import Any

from geonav.errors import ConfigError


@functools.cache
def field_types(cls: type) -> dict[str, Any]:
    """Field name -> resolved type hint of a dataclass (its ``from __future__`` strings
    evaluated)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints.get(f.name, Any) for f in dataclasses.fields(cls)}


def describe(tp: Any) -> str:
    """A type hint in words, for messages: 'a number', 'a list of numbers', 'true or
    false', 'a string or nothing'."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return "any value"
    if tp is bool:
        return "true or false"
    if tp is int:
        return "a whole number"
    if tp is float:
        return "a number"
    if tp is str:
        return "a string"
    if origin in (typing.Union, types.UnionType):
        kinds = [describe(a) for a in args if a is not type(None)]
        text = " or ".join(kinds)
        return text + (" (or left out)" if type(None) in args else "")
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (tuple, list):
        if origin is tuple and args and args[-1] is not Ellipsis:
            return f"a list of {len(args)} ({', '.join(describe(a) for a in args)})"
        inner = args[0] if args else Any
        return f"a list ({describe(inner)} each)"
    if origin in (dict, Mapping) or tp is dict:
        return "a table"
    if dataclasses.is_dataclass(tp):
        return f"a table of {getattr(tp, '__name__', tp)} options"
    return getattr(tp, "__name__", str(tp))


class _Mismatch(Exception):
    """A value does not fit a type hint (internal: turned into ConfigError by callers)."""


def coerce(tp: Any, value: Any, where: str = "") -> Any:
    """``value`` checked against the type hint ``tp`` and converted losslessly (int ->
    float, integral float -> int, list -> tuple, table -> nested config dataclass).

    Raises:
        ConfigError: naming ``where`` (the field), the value and what was expected.
    """
    try:
        return _coerce(tp, value, where)
    except _Mismatch as err:
        raise ConfigError(f"{where} = {value!r}: expected {describe(tp)}"
                          + (f" ({err})" if str(err) else "")) from None


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any or tp is object:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _Mismatch("")
    if tp is int:
        if isinstance(value, bool):
            raise _Mismatch("")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise _Mismatch("")
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _Mismatch("")
        return float(value)
    if tp is str:
        if isinstance(value, str):
            return value
        raise _Mismatch("")
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(a, value, where)
            except (_Mismatch, ConfigError):
                continue
        raise _Mismatch("")
    if origin is typing.Literal:
        if value in args:
            return value
        raise _Mismatch("")
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise _Mismatch("")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise _Mismatch(f"{len(value)} given")
            pairs = enumerate(zip(args, value, strict=True))
            items = [_item(a, v, where, i) for i, (a, v) in pairs]
        else:
            inner = args[0] if args else Any
            items = [_item(inner, v, where, i) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin in (dict, Mapping) or tp is dict:
        if not isinstance(value, dict):
            raise _Mismatch("")
        if len(args) == 2:
            return {k: coerce(args[1], v, f"{where}.{k}") for k, v in value.items()}
        return dict(value)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise _Mismatch("")
        return build(tp, value, where)
    if isinstance(tp, type):
        if isinstance(value, tp):
            return value
        raise _Mismatch("")
    return value  # a hint this checker does not know: left to the dataclass


def _item(tp: Any, value: Any, where: str, i: int) -> Any:
    try:
        return _coerce(tp, value, where)
    except _Mismatch:
        raise _Mismatch(f"item {i + 1} is {value!r}") from None


def check_fields(cls: type, values: Mapping[str, Any], where: str = "",
                 unknown_message: str | None = None) -> dict[str, Any]:
    """``values`` checked against the fields of dataclass ``cls``: unknown keys refused,
    each value coerced to its field's type. Returns the converted mapping.

    Args:
        cls: the config dataclass.
        values: field name -> value as read (TOML, JSON, the command line).
        where: how the user names the table, e.g. ``[a3c]`` or ``[stages.pre]``; prefixed
            to every message.
        unknown_message: the message for unknown keys (default: names them and the known
            ones).
    """
    types_ = field_types(cls)
    unknown = sorted(set(values) - set(types_))
    if unknown:
        raise ConfigError(unknown_message or
                          f"{where + ': ' if where else ''}unknown key(s) {unknown}; "
                          f"known: {sorted(types_)}")
    prefix = f"{where} " if where else ""
    defaults = _dataclass_defaults(cls)
    return {k: coerce(types_[k], _onto_default(defaults.get(k), v), f"{prefix}{k}")
            for k, v in values.items()}


@functools.cache
def _dataclass_defaults(cls: type) -> dict[str, Any]:
    """Field name -> default value, for the fields whose default is a config dataclass
    instance (e.g. PPOConfig's ``loss``)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        value = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out[f.name] = value
    return out


def _onto_default(default: Any, value: Any) -> Any:
    """A partial table for a nested config, filled in from the field's own default rather
    than from the nested class's: ``[ppo.loss] beta = 0`` keeps PPO's GAE lambda 0.95
    (LossConfig's class default is 1.0). Nested tables merge the same way, level by level."""
    if default is None or not isinstance(value, Mapping):
        return value
    merged: dict[str, Any] = {f.name: getattr(default, f.name)
                              for f in dataclasses.fields(default)}
    for k, v in value.items():
        merged[k] = _onto_default(merged.get(k), v) if k in merged else v
    return merged


def build(cls: type, values: Mapping[str, Any], where: str = "",
          unknown_message: str | None = None, **fixed: Any) -> Any:
    """``cls(**fixed, **values)`` after :func:`check_fields`; a ConfigError raised by the
    dataclass's own checks gets ``where`` in front."""
    checked = check_fields(cls, values, where, unknown_message)
    try:
        return cls(**fixed, **checked)
    except ConfigError as err:
        if where and not str(err).startswith(where):
            raise ConfigError(f"{where}: {err}") from err
        raise
