"""Typed params: TOML / command-line values coerced to a stage's params dataclass.

Values arrive in *layers* (stage defaults < workflow ``[params.<stage>]`` < item overrides <
``--set``). Each layer carries its source (for error messages) and the folder its relative
paths are relative to: the workflow file's folder for values from the file, the current
directory for ``--set``. A ``Path``-typed field therefore always ends up absolute, whoever
wrote it.

Supported field types: ``bool``, ``int``, ``float``, ``str``, ``pathlib.Path``,
``Optional[X]`` (``"none"`` or ``"null"`` means ``None``, TOML having no null), ``Literal``,
``tuple[X, ...]`` / ``list[X]``, ``dict[str, X]``, nested frozen dataclasses (TOML tables,
``--set stage.sub.field=v``) and ``Any``.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
import math
import os
import re
import tomllib
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional

from .errors import WorkflowError, unknown_key_hint

_MISSING = object()


@dataclass(frozen=True)
class Layer:
    """One source of values for a params dataclass, as a nested dict."""

    values: Mapping[str, Any]
    source: str  # workflow file path, "--set", or "defaults"
    base_dir: Optional[Path] = None  # relative paths resolve here
    cli: bool = False  # values are raw strings typed on a command line
    prefix: str = ""  # dotted key the values sit under, for messages


@functools.lru_cache(maxsize=None)
def field_types(cls: type) -> dict[str, Any]:
    """Resolved annotations of a dataclass's fields (string annotations included)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints.get(f.name, Any) for f in dataclasses.fields(cls)}


def is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) < len(typing.get_args(tp)):
            inner = args[0] if len(args) == 1 else typing.Union[tuple(args)]  # type: ignore
            return inner, True
    return tp, False


def type_name(tp: Any) -> str:
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


#: The longest ``--set`` value read as a TOML literal; a longer one is a string (a path).
#: (A number of thousands of digits is past Python's digit limit and no param's range.)
MAX_LITERAL_CHARS = 1000


def parse_cli_value(raw: str) -> Any:
    """A ``--set`` value: a TOML literal when it parses as one (``3``, ``true``, ``[1, 2]``),
    else the bare string (``cuda``, ``some/path``)."""
    if len(raw) > MAX_LITERAL_CHARS:
        return raw
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except (ValueError, RecursionError):  # TOMLDecodeError is a ValueError
        return raw


def coerce(value: Any, tp: Any, *, key: str, layer: Layer) -> Any:
    """``value`` converted to ``tp`` or a :class:`WorkflowError` naming ``key`` and its file."""
    if layer.cli and isinstance(value, str):
        parsed = parse_cli_value(value)
        try:
            return _coerce(parsed, tp, key, layer)
        except WorkflowError as first:
            if parsed is value:
                raise
            try:
                return _coerce(value, tp, key, layer)  # e.g. a str field typed as "3"
            except WorkflowError:
                raise first from None  # what was wrong with the value as typed
    return _coerce(value, tp, key, layer)


def short_repr(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters (a 400-digit integer stays readable)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10 ** 60:
        return f"an integer of {len(str(abs(value)))} digits"
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 20]}... ({len(text)} characters)"


def _fail(what: str, value: Any, key: str, layer: Layer) -> WorkflowError:
    return WorkflowError(f"expected {what}, got {short_repr(value)} ({type(value).__name__})",
                         layer.source, key)


def _coerce(value: Any, tp: Any, key: str, layer: Layer) -> Any:
    if tp is Any or tp is object:
        return value
    inner, optional = _unwrap_optional(tp)
    if optional:
        if value is None or (isinstance(value, str) and value.lower() in ("none", "null", "")
                             and inner is not str):
            return None  # "" too: `${VAR:-}` in a workflow leaves an optional value unset
        return _coerce(value, inner, key, layer)
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        choices = typing.get_args(tp)
        for choice in choices:
            if type(value) is type(choice) and value == choice:
                return value
        raise _fail(f"one of {list(choices)}", value, key, layer)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            try:
                return _coerce(value, arg, key, layer)
            except WorkflowError:
                pass
        raise _fail(type_name(tp), value, key, layer)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _fail("true or false", value, key, layer)
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise _fail("an integer", value, key, layer)
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                return float(value)
            except OverflowError:
                raise _fail("a number within the range of a float (about 1.8e308)", value, key, layer) from None
        raise _fail("a number", value, key, layer)
    if tp is str:
        if isinstance(value, str):
            return value
        raise _fail("a string", value, key, layer)
    if isinstance(tp, type) and issubclass(tp, Path):
        if isinstance(value, (str, os.PathLike)):
            path = Path(os.path.expanduser(os.fspath(value)))
            if not path.is_absolute() and layer.base_dir is not None:
                path = Path(os.path.normpath(layer.base_dir / path))
            return path
        raise _fail("a path (string)", value, key, layer)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        for member in tp:
            if value == member.value or value == member.name:
                return member
        raise _fail(f"one of {[m.value for m in tp]}", value, key, layer)
    if origin in (tuple, list, typing.Sequence) or tp in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise _fail(f"an array ({type_name(tp)})", value, key, layer)
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis or len(args) == 1:
            items = [_coerce(v, args[0], f"{key}[{i}]", layer) for i, v in enumerate(value)]
        elif args:
            if len(args) != len(value):
                raise _fail(f"an array of {len(args)} values", value, key, layer)
            items = [_coerce(v, a, f"{key}[{i}]", layer) for i, (v, a) in
                     enumerate(zip(value, args))]
        else:
            items = list(value)
        return items if origin is list or tp is list else tuple(items)
    if origin in (dict, typing.Mapping) or tp is dict:
        if not isinstance(value, Mapping):
            raise _fail("a table", value, key, layer)
        args = typing.get_args(tp) or (str, Any)
        return {str(k): _coerce(v, args[1], f"{key}.{k}", layer) for k, v in value.items()}
    if is_dataclass_type(tp):
        if not isinstance(value, Mapping):
            raise _fail(f"a table ({tp.__name__})", value, key, layer)
        return build(tp, [dataclasses.replace(layer, values=value, prefix=key)], owner=key)
    if isinstance(value, tp):
        return value
    raise _fail(type_name(tp), value, key, layer)


def _flatten(cls: type, values: Mapping[str, Any], layer: Layer, prefix: str,
             out: dict[tuple[str, ...], tuple[Any, Layer, str]], path: tuple[str, ...]) -> None:
    types_ = field_types(cls)
    for name, value in values.items():
        key = f"{prefix}.{name}" if prefix else name
        if name not in types_:
            raise WorkflowError(f"unknown param {name!r} of {cls.__name__}"
                                + unknown_key_hint(name, types_), layer.source, key)
        tp = types_[name]
        if is_dataclass_type(tp) and isinstance(value, Mapping):
            _flatten(tp, value, layer, key, out, path + (name,))
        else:
            out[path + (name,)] = (value, layer, key)


def check(cls: type, layer: Layer) -> None:
    """Validate one layer's keys and value types against ``cls`` without building it
    (so a layer that sets only some of the required fields can be checked alone)."""
    for path, (value, lay, key) in set_values(cls, [layer]).items():
        owner, tp = cls, Any
        for name in path:
            tp = field_types(owner)[name]
            owner = tp
        coerce(value, tp, key=key, layer=lay)


def build(cls: type, layers: list[Layer], owner: str, base: Any = _MISSING) -> Any:
    """An instance of ``cls`` from its defaults and ``layers`` (later layers win).

    Args:
        cls: a dataclass type.
        layers: value layers, lowest precedence first.
        owner: what the params belong to (``"stage 'train'"``), for messages.
        base: an instance to start from instead of the class defaults.
    """
    return _assemble(cls, set_values(cls, layers), (), owner, base)


def set_values(cls: type, layers: list[Layer]) -> dict[tuple[str, ...], tuple[Any, Layer, str]]:
    """Every value ``layers`` set, by field path: ``(value, the layer that set it last, its
    dotted key)``."""
    leaves: dict[tuple[str, ...], tuple[Any, Layer, str]] = {}
    for layer in layers:
        _flatten(cls, layer.values, layer, layer.prefix, leaves, ())
    return leaves


def first_named(candidates: Iterable[tuple[str, Any]], message: str) -> Any:
    """The value of the candidate ``(name, value)`` whose name ``message`` mentions first
    (as a whole word); None when it names none. How a refused value is traced back to the
    key that set it: the checks name the field they refuse."""
    best = None
    for name, value in candidates:
        m = re.search(rf"(?<![A-Za-z0-9_]){re.escape(name)}(?![A-Za-z0-9_])", message)
        if m and (best is None or m.start() < best[0]):
            best = (m.start(), value)
    return best[1] if best else None


def _assemble(cls: type, leaves: dict, path: tuple[str, ...], owner: str, base: Any) -> Any:
    kwargs: dict[str, Any] = {}
    types_ = field_types(cls)
    for f in dataclasses.fields(cls):
        tp = types_[f.name]
        here = path + (f.name,)
        if here in leaves:
            value, layer, key = leaves[here]
            kwargs[f.name] = coerce(value, tp, key=key, layer=layer)
        elif is_dataclass_type(tp) and any(k[: len(here)] == here for k in leaves):
            if base is not _MISSING:
                sub_base = getattr(base, f.name)
            elif f.default is not dataclasses.MISSING:
                sub_base = f.default
            elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
                sub_base = f.default_factory()  # type: ignore[misc]
            else:
                sub_base = _MISSING
            kwargs[f.name] = _assemble(tp, leaves, here, owner, sub_base)
        elif base is _MISSING and f.default is dataclasses.MISSING and \
                f.default_factory is dataclasses.MISSING and f.init:  # type: ignore[misc]
            raise WorkflowError(f"{owner}: param {'.'.join(here)!r} ({type_name(tp)}) has no "
                                "default and the workflow does not set it")
    try:
        return dataclasses.replace(base, **kwargs) if base is not _MISSING else cls(**kwargs)
    except (TypeError, ValueError) as exc:  # the dataclass's own __post_init__ checks
        # Name where the offending value was set: the fields the message mentions, else the
        # values set at this level (the check cannot say which one it refused).
        msg = str(exc)
        set_here = [(f.name, leaves[path + (f.name,)]) for f in dataclasses.fields(cls)
                    if path + (f.name,) in leaves]
        named = first_named(((x[0], x) for x in set_here), msg)
        culprits = [named] if named is not None else set_here
        if len(culprits) == 1:
            _, (_, layer, key) = culprits[0]
            who = owner.removeprefix(f"{layer.source}: ")
            raise WorkflowError(f"{who}: {msg}" if who != owner or not key.startswith(who) else msg,
                                layer.source, key) from exc
        where = "; ".join(f"{layer.source}: {key}" for _, (_, layer, key) in culprits)
        raise WorkflowError(f"{owner}: invalid params {cls.__name__}: {msg}"
                            + (f" (values set at {where})" if where else "")) from exc


def to_json(value: Any) -> Any:
    """A JSON-able, canonical form of a params value (paths as strings, tuples as lists)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Path):
        return os.fspath(value)
    if isinstance(value, enum.Enum):
        return to_json(value.value)
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)  # canonical JSON has no inf/nan
    return value


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    return json.dumps(str(value))  # TOML basic strings share JSON's escapes


def defaults_toml(cls: type, table: str) -> str:
    """The defaults of ``cls`` as a TOML table ``[table]`` (required fields commented)."""
    lines = [f"[{table}]"]
    nested: list[str] = []
    types_ = field_types(cls)
    for f in dataclasses.fields(cls):
        tp = types_[f.name]
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = f.default_factory()  # type: ignore[misc]
        else:
            lines.append(f"# {f.name} = ...  # required ({type_name(tp)})")
            continue
        valid = valid_values(cls, f.name, tp)
        if is_dataclass_type(tp):
            nested.append(defaults_toml(tp, f"{table}.{f.name}"))
        elif default is None:
            note = "; ".join(x for x in (valid, f.metadata.get("help") if f.metadata else None) if x)
            lines.append(f"# {f.name} = ...  # default: none ({type_name(tp)})" + (f"; {note}" if note else ""))
        else:
            note = "; ".join(x for x in (valid, f.metadata.get("help") if f.metadata else None) if x)
            lines.append(f"{f.name} = {_toml_value(to_json(default))}" + (f"  # {note}" if note else ""))
    return "\n".join(lines + ([""] + nested if nested else []))


def valid_values(cls: type, name: str, tp: Any) -> str:
    """The valid values of a params field in words, from the class's ``RANGES`` (numeric
    intervals, "[0, 1)" ...) and ``CHOICES`` attributes — the convention the params classes
    follow and enforce in ``__post_init__``; a float without a range must be finite."""
    choices = (getattr(cls, "CHOICES", None) or {}).get(name)
    if choices is not None:
        return "one of " + ", ".join(str(c) for c in choices)
    interval = (getattr(cls, "RANGES", None) or {}).get(name)
    if interval is not None:
        return f"in {interval}"
    inner, _ = _unwrap_optional(tp)
    if inner is float:
        return "finite"
    return ""
