"""Shared fixtures: paths to the read-only shared data and a device parameter."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

# Set before any test module imports torch: on this shared, oversubscribed machine the
# default spinning OpenMP workers cost 10-30x the CPU time of the work itself
# (measured on a tiny training step: 121 ms vs 3.8 ms CPU per iteration).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# A test session started as a background job of a non-interactive shell (`cmd &` in a
# script, as CI runners may do) inherits SIGINT *ignored*; then the Ctrl-C tests can
# neither interrupt this process (_thread.interrupt_main does nothing) nor the runs they
# start (an ignored signal stays ignored across exec). Python's own handler restores what
# an interactive terminal gives; child processes get the default action after exec.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("COBGS_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The read-only real scenes (../shared/data); tests that need them skip without."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (set COBGS_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture(params=["cpu", "cuda"])
def device(request):
    """Runs a test on every available device; CUDA is skipped where absent."""
    import torch

    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    return request.param
