"""What a stage's ``run(ctx, inputs)`` receives besides its inputs."""

from __future__ import annotations

import logging
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Optional

from .items import Item
from .values import Settings


@dataclass
class StageContext:
    """The run context of one task.

    Attributes:
        stage: the stage name.
        item: the item this task runs for (``ctx.item["scene"]``, ``ctx.item.attrs``); the
            root item for a per-workflow stage.
        items: the workflow's full items (every axis) that this task's item covers:
            all of them for a per-workflow stage, a scene's scene x method items for a
            per-scene stage, ``[item]`` for a stage running over every axis.
        params: the stage's params dataclass, resolved for this item.
        settings: workflow-wide settings (``ctx.settings.device``, also ``ctx.device``).
        out_dir: write outputs here (inside the entry's temporary folder); return their
            paths. Nothing here is visible to anyone until the entry is committed.
        scratch_dir: a private temporary folder, deleted before the entry is committed.
        log: a logger writing to the entry's ``log.txt`` (kept for failures too).
        key: the cache key of this task.
    """

    stage: str
    item: Item
    items: list[Item]
    params: Any
    settings: Settings
    out_dir: Path
    scratch_path: Path
    log: logging.Logger
    key: str
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def scratch_dir(self) -> Path:
        """A private temporary folder (created on first use), deleted before commit."""
        self.scratch_path.mkdir(exist_ok=True)
        return self.scratch_path

    @property
    def device(self) -> str:
        return self.settings.device

    def note(self, **values: Any) -> None:
        """Record JSON-able values (e.g. GPU peak memory, iteration counts) in the
        manifest's ``extra`` section."""
        self.extra.update(values)

    def warn(self, message: str) -> None:
        """Something the user should see although the task succeeded: kept in the
        manifest (``extra["warnings"]``), logged, and shown on the task's progress line
        (also when the entry is later reused from the cache)."""
        self.extra.setdefault("warnings", []).append(message)
        self.log.warning(message)

    def progress(self, iterable: Optional[Iterable] = None, total: Optional[int] = None,
                 desc: Optional[str] = None, unit: str = "it") -> Any:
        """Inner progress: a tqdm bar on an interactive terminal, else log lines every
        ~10 % (or 30 s). Use as ``for x in ctx.progress(xs): ...`` or as a context
        manager with ``.update(n)``."""
        who = f"{self.stage}[{self.item.label}]"
        desc = desc or who
        if sys.stderr.isatty():
            try:
                from tqdm import tqdm

                return tqdm(iterable, total=total, desc=desc, unit=unit, leave=False)
            except ImportError:  # tqdm is optional for the engine
                pass
        return _LogProgress(iterable, total, desc if desc.startswith(who) else f"{who} {desc}", self.log)


class _LogProgress:
    """Progress for non-interactive runs: a console line (standard error, which a forked
    worker shares with the run and Ray forwards to the driver) every few seconds
    (``$COBGS_PROGRESS_INTERVAL_S``, default 5) with the count, the stage's own figures
    (``set_postfix``: loss, Gaussians ...) and an ETA; and a log line at every ~10 %."""

    def __init__(self, iterable: Optional[Iterable], total: Optional[int], desc: str,
                 log: logging.Logger):
        self.iterable, self.desc, self.log = iterable, desc, log
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total, self.n = total, 0
        self.postfix: dict[str, Any] = {}
        self._t0 = self._last_t = self._last_print = time.monotonic()
        self._last_frac = 0.0
        try:
            self.interval = float(os.environ.get("COBGS_PROGRESS_INTERVAL_S", "5"))
        except ValueError:
            self.interval = 5.0

    def _text(self, now: float) -> str:
        parts = [f"{self.desc}: {self.n}" + (f"/{self.total} ({100 * self.n / self.total:.0f}%)"
                                             if self.total else "")]
        parts += [f"{k} {v}" for k, v in self.postfix.items()]
        if self.total and 0 < self.n < self.total:
            eta = (now - self._t0) / self.n * (self.total - self.n)
            parts.append(f"ETA {eta:.0f} s" if eta < 120 else f"ETA {eta / 60:.1f} min")
        return ", ".join(parts)

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        frac = self.n / self.total if self.total else 0.0
        if frac - self._last_frac >= 0.1 or now - self._last_t >= 30 or frac >= 1:
            self.log.info("%s", self._text(now))
            self._last_t, self._last_frac = now, frac
        if now - self._last_print >= self.interval:
            self._last_print = now
            try:
                print(f"  {self._text(now)}", file=sys.__stderr__ or sys.stderr, flush=True)
            except (OSError, ValueError):  # a closed console must not fail the task
                pass

    def __iter__(self) -> Iterator:
        for x in self.iterable or ():
            yield x
            self.update()

    def __enter__(self) -> "_LogProgress":
        return self

    def __exit__(self, *exc: Any) -> None:
        pass

    def close(self) -> None:
        pass

    def set_postfix(self, *args: Any, **kwargs: Any) -> None:
        if args and isinstance(args[0], dict):
            self.postfix.update(args[0])
        self.postfix.update(kwargs)
