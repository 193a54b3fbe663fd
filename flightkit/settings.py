"""TOML tables validated into frozen dataclasses: the generic loader every config section uses.

A section is a frozen dataclass whose fields carry :func:`setting` metadata (a help phrase, a
numeric range, a tuple length); :func:`load_section` validates a table into it and raises
:class:`~flightkit.errors.ConfigError` naming the file, the key, the bad value and the fix on an
unknown key, a missing required key, a wrong type or an out-of-range value. The lab's own
sections are in :mod:`flightkit.config`; capability packages (trajectories, capture, estimation)
describe theirs the same way.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import tomllib
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import field
from pathlib import Path
from typing import Any, TypeVar, overload

from flightkit.errors import ConfigError

__all__ = ["load_section", "load_toml", "setting"]

T = TypeVar("T")


@overload
def setting(
    default: T,
    *,
    help: str = "",
    min: float | None = None,
    max: float | None = None,
    length: int | None = None,
) -> T: ...


@overload
def setting(
    *,
    help: str = "",
    min: float | None = None,
    max: float | None = None,
    length: int | None = None,
    default_factory: Callable[[], T],
) -> T: ...


@overload
def setting(
    *,
    help: str = "",
    min: float | None = None,
    max: float | None = None,
    length: int | None = None,
) -> Any: ...  # a required key: as with dataclasses.field, the field's annotation gives the type


def setting(
    default: Any = dataclasses.MISSING,
    *,
    help: str = "",
    min: float | None = None,
    max: float | None = None,
    length: int | None = None,
    default_factory: Any = dataclasses.MISSING,
) -> Any:
    """A dataclass field with validation metadata.

    Args:
        default: default value (omit for a required key).
        help: one phrase shown in errors, e.g. "metres above the floor".
        min, max: inclusive numeric range (for numbers, and for each element of a tuple).
        length: required length for tuple values.
        default_factory: as in :func:`dataclasses.field`.
    """
    meta = {"help": help, "min": min, "max": max, "length": length}
    if default_factory is not dataclasses.MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


def _type_name(tp: Any) -> str:
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return "one of " + ", ".join(repr(m.value) for m in tp)
    if isinstance(tp, type):
        return {"float": "a number", "int": "an integer", "str": "a string", "bool": "true or false"}.get(
            tp.__name__, tp.__name__
        )
    return str(tp)


def _convert(value: Any, tp: Any, meta: Mapping[str, Any], path: str, key: str) -> Any:
    origin = typing.get_origin(tp)
    help_ = meta.get("help", "")
    fix_hint = f" ({help_})" if help_ else ""

    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(value, args[0], meta, path, key)

    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, Mapping):
            raise ConfigError(path, key, f"expected a table, got {value!r}", f"write it as [{key}]", value)
        return load_section(tp, value, path=path, prefix=key)

    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(path, key, f"expected a list, got {value!r}", f"give a list{fix_hint}", value)
        elem_tp = typing.get_args(tp)[0]
        length = meta.get("length")
        if length is not None and len(value) != length:
            raise ConfigError(
                path, key, f"expected {length} values, got {len(value)}", f"give exactly {length}{fix_hint}", value
            )
        return tuple(_convert(v, elem_tp, meta, path, f"{key}[{i}]") for i, v in enumerate(value))

    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(path, key, f"expected a table, got {value!r}", f"write it as [{key}]", value)
        val_tp = typing.get_args(tp)[1] if typing.get_args(tp) else str
        if val_tp is str:
            return {str(k): str(v) for k, v in value.items()}
        return {str(k): _convert(v, val_tp, {}, path, f"{key}.{k}") for k, v in value.items()}

    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        for member in tp:
            if value == member.value:
                return member
        raise ConfigError(path, key, f"{value!r} is not allowed", f"use {_type_name(tp)}", value)

    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(path, key, f"expected true or false, got {value!r}", "write true or false", value)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, key, f"expected an integer, got {value!r}", f"give a whole number{fix_hint}", value)
        _check_range(value, meta, path, key)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(path, key, f"expected a number, got {value!r}", f"give a number{fix_hint}", value)
        if not math.isfinite(float(value)):
            raise ConfigError(path, key, f"{value!r} is not finite", f"give a finite number{fix_hint}", value)
        _check_range(float(value), meta, path, key)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(path, key, f"expected a string, got {value!r}", f'quote it: "...{fix_hint}"', value)
        return value
    raise TypeError(f"config type {tp!r} of {key} is not supported by the loader")


def _check_range(value: float, meta: Mapping[str, Any], path: str, key: str) -> None:
    lo, hi = meta.get("min"), meta.get("max")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        lo_s = "-inf" if lo is None else f"{lo:g}"
        hi_s = "inf" if hi is None else f"{hi:g}"
        help_ = meta.get("help", "")
        raise ConfigError(
            path,
            key,
            f"{value!r} is out of range [{lo_s}, {hi_s}]",
            f"give a value from {lo_s} to {hi_s}" + (f" ({help_})" if help_ else ""),
            value,
        )


def load_section(cls: type[T], table: Mapping[str, Any], *, path: str = "<dict>", prefix: str = "") -> T:
    """Validate a TOML table into the frozen dataclass ``cls``.

    Raises:
        ConfigError: on unknown keys, missing required keys, wrong types, out-of-range values.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init and not f.metadata.get("init_only_loader")}
    dotted = (prefix + ".") if prefix else ""
    unknown = [k for k in table if k not in fields]
    if unknown:
        known = ", ".join(sorted(fields)) or "(none)"
        raise ConfigError(
            path, dotted + unknown[0], "unknown key", f"remove it or use one of: {known}", table[unknown[0]]
        )
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        key = dotted + name
        if name in table:
            kwargs[name] = _convert(table[name], hints[name], f.metadata, path, key)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(path, key, "missing required key", f"add {name} = ... ({f.metadata.get('help', '')})")
    obj = cls(**kwargs)
    check = getattr(cls, "_check", None)
    if callable(check):
        check(obj, path, prefix)
    return obj


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file, turning IO and syntax errors into ConfigError."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(str(p), "(file)", "file not found", "check the path") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), "(syntax)", f"invalid TOML: {exc}", "fix the TOML syntax") from exc
    except OSError as exc:
        raise ConfigError(str(p), "(file)", f"cannot read: {exc.strerror}", "check permissions") from exc
