"""The range checker every config uses (each range stated once, as RANGES / CHOICES on its
class) and the "added later" rule that keeps earlier cache keys."""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any, Mapping, Optional

from cobgs.errors import InputError


# -- valid ranges ------------------------------------------------------------------------
# Every config (and the pipeline's stage params) states the valid range of its numeric
# fields once, as a class attribute RANGES = {field: "[lo, hi]"} ("(" / ")" for an open
# end, inf allowed), and the allowed values of its string fields as CHOICES; check_params
# enforces both in __post_init__, and the docs' table of params is generated from them
# (docs/pipeline.md, `cobgs stages --toml`). A float field without a range must be finite.
_INTERVAL = re.compile(r"^\s*([\[(])\s*([^,\s]+)\s*,\s*([^\])\s]+)\s*([\])])\s*$")


def parse_interval(text: str) -> tuple[float, float, bool, bool]:
    """(lo, hi, lo_closed, hi_closed) of an interval written "[0, 1)", "(0, inf]" ..."""
    m = _INTERVAL.match(text)
    if m is None:
        raise ValueError(f"bad interval {text!r} (expected e.g. '[0, 1]' or '(0, inf)')")
    return float(m.group(2)), float(m.group(3)), m.group(1) == "[", m.group(4) == "]"


def in_interval(x: float, text: str) -> bool:
    lo, hi, lo_c, hi_c = parse_interval(text)
    if x != x:  # nan
        return False
    return (x >= lo if lo_c else x > lo) and (x <= hi if hi_c else x < hi)


def check_params(obj) -> None:
    """Enforce ``type(obj).RANGES`` / ``CHOICES`` (see above) on a dataclass instance.

    Raises:
        InputError: naming the class, the field, the valid range or values, and the value.
    """
    cls = type(obj)
    ranges = getattr(cls, "RANGES", {})
    choices = getattr(cls, "CHOICES", {})
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        kind = _NUMBER_TYPES.get(f.type if isinstance(f.type, str) else getattr(f.type, "__name__", ""))
        if kind is not None and v is not None and (isinstance(v, bool) or not isinstance(v, kind)):
            what = "an integer" if kind is int else "a number"
            raise InputError(f"{cls.__name__}.{f.name} must be {what}" + (f" in {ranges[f.name]}" if f.name in ranges
                                                                           else "") + f", got {_short(v)}")
        allowed = choices.get(f.name)
        if allowed is not None and v is not None and v not in allowed:
            raise InputError(f"{cls.__name__}.{f.name} must be one of {list(allowed)}, got {v!r}")
        spec = ranges.get(f.name)
        for x in (v if isinstance(v, (tuple, list)) else (v,)):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                continue
            try:
                fx = float(x)
            except OverflowError:  # an int past any float: outside every range
                fx = math.inf if x > 0 else -math.inf
            if spec is not None:
                if not in_interval(fx, spec):
                    raise InputError(f"{cls.__name__}.{f.name} must be in {spec}, got {_short(x)}")
            elif not math.isfinite(fx):
                raise InputError(f"{cls.__name__}.{f.name} must be a finite number, got {_short(x)}")


#: Field annotations (as written: ``from __future__ import annotations``) whose values
#: check_params also checks the type of: an int field takes an int, a float field a number.
_NUMBER_TYPES = {"int": int, "Optional[int]": int, "float": (int, float), "Optional[float]": (int, float)}


def _short(x) -> str:
    """A value for a message: a huge integer by its digit count, not its digits."""
    if isinstance(x, int) and abs(x) >= 10 ** 60:
        return f"an integer of {len(str(abs(x)))} digits"
    return repr(x)


def with_later_values(cls, params: dict) -> dict:
    """``params`` (a params object as JSON, as a manifest recorded it) with each field of
    ``cls`` added later and absent there filled in with the value runs had before it existed
    (field metadata "before"): an entry written before a switch reads as what it ran."""
    out = dict(params)
    for f in dataclasses.fields(cls):
        if "before" in f.metadata and f.name not in out:
            before = f.metadata["before"]
            out[f.name] = list(before) if isinstance(before, tuple) else before
    return out


def key_without_later(cls, full: dict, forced: Optional[Mapping[str, Any]] = None) -> dict:
    """``full`` (a params object as JSON) without the fields of ``cls`` that were added
    later and hold the value every run had before they existed (field metadata "before"):
    a cache key made this way is the key the same run had before the field was added.

    A field whose metadata has ``"only_with": (name, values)`` only acts while field ``name``
    holds one of ``values``; otherwise it says nothing of the run and leaves the key whatever
    it holds (a sub-option of a switch that is off). ``forced``: values a method imposes over
    ``full``'s (a row that runs with a switch off whatever its params say)."""
    out = dict(full)
    effective = {**full, **(forced or {})}
    for f in dataclasses.fields(cls):
        if f.name not in out:
            continue
        only = f.metadata.get("only_with")
        if only is not None and effective.get(only[0]) not in only[1]:
            del out[f.name]
            continue
        if "before" in f.metadata:
            before = f.metadata["before"]
            if out[f.name] == (list(before) if isinstance(before, tuple) else before):
                del out[f.name]
    return out

