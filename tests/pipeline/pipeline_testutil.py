"""Helpers shared by the engine tests (a plain module: ``from conftest import`` would be
ambiguous with several conftest.py files on the path)."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


class Executions:
    """Reads the ``$PIPELINE_TOYS_LOG`` file the toy stages append to."""

    def __init__(self, path: Path):
        self.path = path

    def lines(self) -> list[str]:
        return self.path.read_text().splitlines() if self.path.exists() else []

    def count(self) -> Counter:
        return Counter(self.lines())

    def stages(self) -> Counter:
        return Counter(line.split(" ")[0] for line in self.lines())

    def reset(self) -> None:
        self.path.unlink(missing_ok=True)


def cli_env(**extra: str) -> dict[str, str]:
    """Environment for running ``cobgs`` in a subprocess with the toy stages plugged in."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(HERE), str(REPO), env.get("PYTHONPATH", "")])
    env["COBGS_STAGE_MODULES"] = "pipeline_toys"
    env["COBGS_BUILTIN_STAGES"] = "0"  # the toys reuse the program's stage names
    env.pop("COBGS_CACHE_DIR", None)
    env.update(extra)
    return env
