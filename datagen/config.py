"""Strict loading of nested dataclasses from YAML/JSON mappings.

Unknown keys, wrong types and out-of-range values are errors naming the file and the dotted
field path (e.g. `motion.actions.walk`), never silently ignored or clamped.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

from datagen.errors import InputError

T = TypeVar("T")


class _Loader(yaml.SafeLoader):
    """PyYAML follows YAML 1.1, whose floats need a dot and a signed exponent: `1e-3` and
    `1.0e12` load as strings there and then fail as "expected a number". YAML 1.2 (and so most
    other readers) takes them as floats; so does this loader (only exponent forms are added)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def load_yaml(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "an existing YAML file", "no such file")
    try:
        data = yaml.load(path.read_text(), Loader=_Loader)  # noqa: S506 (a safe loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "document"
        raise InputError(path, where, "valid YAML", str(getattr(exc, "problem", exc))) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(path, None, "a mapping at the top level", type(data).__name__)
    return data


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return " or ".join(repr(a) for a in get_args(tp))
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if origin in (list, tuple):
        args = get_args(tp)
        return f"a list of {_type_name(args[0])}" if args else "a list"
    if origin is dict:
        args = get_args(tp)
        return f"a mapping of {_type_name(args[1])}" if args else "a mapping"
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def _convert(tp: Any, value: Any, source: str | Path | None, path: str) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        for arg in get_args(tp):
            try:
                return _convert(arg, value, source, path)
            except InputError:
                continue
        raise InputError(source, path, _type_name(tp), value)
    if tp is type(None):
        if value is None:
            return None
        raise InputError(source, path, "null", value)
    if origin is Literal:
        if value in get_args(tp):
            return value
        raise InputError(source, path, _type_name(tp), value)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise InputError(source, path, "a mapping", value)
        return from_mapping(tp, value, source, path)
    if tp is dict:  # a section parsed by its own stage (e.g. the outfit): a mapping, as given
        if not isinstance(value, dict):
            raise InputError(source, path, "a mapping", value)
        return dict(value)
    if origin is dict:
        key_t, val_t = get_args(tp)
        if not isinstance(value, dict):
            raise InputError(source, path, _type_name(tp), value)
        out = {}
        for k, v in value.items():
            k2 = _convert(key_t, k, source, f"{path}.{k}" if path else str(k))
            out[k2] = _convert(val_t, v, source, f"{path}.{k}" if path else str(k))
        return out
    if origin in (list, tuple):
        args = get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise InputError(source, path, _type_name(tp), value)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise InputError(source, path, f"a list of {len(args)} values", value)
            return tuple(
                _convert(a, v, source, f"{path}[{i}]")
                for i, (a, v) in enumerate(zip(args, value, strict=True))
            )
        item_t = args[0] if args else Any
        items = [_convert(item_t, v, source, f"{path}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise InputError(source, path, "true or false", value)
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise InputError(source, path, "an integer", value)
    if tp is float:
        # NaN passes every range check (each comparison is false) and infinity every open
        # one; neither is a setting, and either would surface frames later as a blow-up.
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                number = float(value)
            except OverflowError:  # an int past float's range
                number = math.inf
            if math.isfinite(number):
                return number
            raise InputError(source, path, "a finite number", value)
        raise InputError(source, path, "a number", value)
    if tp is str:
        if isinstance(value, str):
            return value
        raise InputError(source, path, "a string", value)
    raise TypeError(f"unsupported config type {tp!r} at {path}")


def from_mapping(cls: type[T], data: dict, source: str | Path | None = None, path: str = "") -> T:
    """Build dataclass `cls` from `data`, rejecting unknown keys and wrong types.

    A dataclass may define `validate(self, source, path)` for range checks; it is called after
    construction.
    """
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in fields]
    if unknown:
        key = unknown[0]
        raise InputError(
            source,
            f"{path}.{key}" if path else str(key),
            f"one of the known keys ({', '.join(sorted(fields))})",
            key,
        )
    kwargs = {}
    for name, field in fields.items():
        sub = f"{path}.{name}" if path else name
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], source, sub)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise InputError(source, sub, f"a value ({_type_name(hints[name])})", "missing")
    obj = cls(**kwargs)
    validate = getattr(obj, "validate", None)
    if callable(validate):
        validate(source, path)
    return obj


def to_mapping(obj: Any) -> Any:
    """Dataclasses -> plain dicts/lists (tuples become lists), for JSON/YAML."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_mapping(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {k: to_mapping(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_mapping(v) for v in obj]
    return obj


def check_range(
    value: float, lo: float | None, hi: float | None, source: str | Path | None, path: str
) -> None:
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        lo_s = "-inf" if lo is None else f"{lo:g}"
        hi_s = "inf" if hi is None else f"{hi:g}"
        raise InputError(source, path, f"a value in [{lo_s}, {hi_s}]", value)
