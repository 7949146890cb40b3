"""`import cobgs` sets OpenMP's passive wait policy for a library user (issue 45, item 5): the
runtime reads it once, when torch loads it, so it applies only before torch is imported and
only where the user set nothing (tests/benchmarks/bm_omp_wait.py measures what it buys)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _policy(code: str, **env) -> str:
    e = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    e.update(env)
    return subprocess.run([sys.executable, "-c", code + "; import os; print(os.environ.get('OMP_WAIT_POLICY'))"],
                          env=e, capture_output=True, text=True, check=True, cwd=REPO).stdout.strip()


def test_import_cobgs_sets_passive_only_when_it_can_take_effect():
    assert _policy("import cobgs") == "PASSIVE"
    assert _policy("import cobgs", OMP_WAIT_POLICY="ACTIVE") == "ACTIVE"  # the user's choice stays
    assert _policy("import torch, cobgs") == "None"  # too late: the runtime has read it already
