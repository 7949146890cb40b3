"""Number formatting for the report: one place decides precision and units.

Every formatter returns "" for a missing or non-finite value, so that "not measured" is
an empty cell and never a made-up 0.
"""

from __future__ import annotations

import math
import time
from typing import Any, Optional


def finite(x: Any) -> Optional[float]:
    """``x`` as a float when it is a finite number, else None."""
    if x is None or isinstance(x, bool):
        return None
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def pct(x: Any, digits: int = 2) -> str:
    """A fraction in [0, 1] as a percentage without the sign (paper style: 92.10)."""
    f = finite(x)
    return "" if f is None else f"{100.0 * f:.{digits}f}"


def quoted_pct(x: Any) -> str:
    """A percentage quoted from the paper, printed as the paper printed it (one decimal)."""
    f = finite(x)
    return "" if f is None else f"{f:.1f}"


def db(x: Any, digits: int = 2, signed: bool = False) -> str:
    f = finite(x)
    if f is None:
        return ""
    return f"{f:+.{digits}f}" if signed else f"{f:.{digits}f}"


def count(x: Any) -> str:
    """An integer with thin-space thousands separators (12 345)."""
    f = finite(x)
    return "" if f is None else f"{int(round(f)):,}".replace(",", "\u2009")


def seconds(x: Any) -> str:
    f = finite(x)
    if f is None:
        return ""
    if f < 1.0:
        return f"{1000.0 * f:.0f} ms"
    if f < 120.0:
        return f"{f:.1f} s"
    if f < 7200.0:
        return f"{int(f // 60)} min {int(round(f % 60)):02d} s"
    return f"{f / 3600.0:.1f} h"


def nbytes(x: Any) -> str:
    f = finite(x)
    if f is None:
        return ""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(f) < 1024.0 or unit == "TiB":
            return f"{f:.0f} {unit}" if unit == "B" else f"{f:.1f} {unit}"
        f /= 1024.0
    return ""


def timestamp(t: Any) -> str:
    f = finite(t)
    return "" if f is None else time.strftime("%Y-%m-%d %H:%M:%S %Z", time.localtime(f))


def short_key(key: Optional[str]) -> str:
    return (key or "")[:12]
