"""The CUDA blending path switch (csrc/blend/fast_path.cpp): the fast path is the default,
``COBGS_CUDA_EXACT=1`` selects the exact one at load, ``cuda_fast_path`` switches within a
block and restores the previous setting. The switch exists in every build (a CPU-only one
too, where nothing reads it), so this runs without a GPU."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
_PRINT = "from cobgs.render._ops import cuda_fast_path_on; print(cuda_fast_path_on())"


@pytest.mark.parametrize("value, fast", [(None, True), ("", True), ("0", True), ("1", False)])
def test_the_environment_picks_the_path_at_load(value, fast):
    env = {k: v for k, v in os.environ.items() if k != "COBGS_CUDA_EXACT"}
    if value is not None:
        env["COBGS_CUDA_EXACT"] = value
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", _PRINT], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(fast)


def test_the_block_switches_and_restores():
    from cobgs.render._ops import cuda_fast_path, cuda_fast_path_on

    before = cuda_fast_path_on()
    with cuda_fast_path(not before):
        assert cuda_fast_path_on() is (not before)
        with cuda_fast_path(before):
            assert cuda_fast_path_on() is before
        assert cuda_fast_path_on() is (not before)
    assert cuda_fast_path_on() is before
    with pytest.raises(RuntimeError):
        with cuda_fast_path(not before):
            raise RuntimeError("inside")
    assert cuda_fast_path_on() is before
