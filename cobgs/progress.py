"""Progress bars for the long library loops (refinement, peers).

``progress`` arguments across :mod:`cobgs` take ``False`` (silent), ``True`` (a tqdm bar on
standard error) or a factory ``progress(total=, desc=)`` returning an object with
``update(n)``, ``set_postfix(**values)`` and ``close()`` — how a pipeline stage hands in
its own progress (log lines with an ETA when no terminal is attached).
"""

from __future__ import annotations

from typing import Any, Callable, Union

Progress = Union[bool, Callable[..., Any]]


def make_bar(progress: Progress, total: int, desc: str) -> Any:
    """The bar ``progress`` asks for, or None."""
    if not progress:
        return None
    if callable(progress):
        return progress(total=total, desc=desc)
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, dynamic_ncols=True)
