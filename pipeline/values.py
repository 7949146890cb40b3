"""Value types shared across the engine, in a module that imports nothing of it.

``Settings`` is read by the workflow loader, the task context and the stages' resource
functions; keeping it here lets those modules form a layered order (no import cycle:
tests/pipeline/test_pipeline_layers.py walks the imports).
"""

from __future__ import annotations

import re
from dataclasses import dataclass


@dataclass(frozen=True)
class Settings:
    """Workflow-wide settings every stage can read from ``ctx.settings``."""

    device: str = "cpu"

    def __post_init__(self) -> None:
        if not re.fullmatch(r"cpu|cuda(:\d+)?", self.device):
            raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")
