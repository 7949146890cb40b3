"""The blending path switches (csrc/blend/fast_path.cpp). CUDA: the fast path is the default,
``COBGS_CUDA_EXACT=1`` selects the exact one at load. CPU: the exact path is the default,
``COBGS_CPU_FAST=1`` selects the fast one at load. ``cuda_fast_path`` / ``cpu_fast_path``
switch within a block and restore the previous setting. Both switches exist in every build
(a CPU-only one too, where nothing reads the CUDA one), so this runs without a GPU."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# kind -> (the variable read at load, {its value (None: unset): the fast path on?})
SWITCHES = {
    "cuda": ("COBGS_CUDA_EXACT", {None: True, "": True, "0": True, "1": False}),
    "cpu": ("COBGS_CPU_FAST", {None: False, "": False, "0": False, "1": True}),
}


def _switch(kind):
    from cobgs.render import ops

    return getattr(ops, f"{kind}_fast_path"), getattr(ops, f"{kind}_fast_path_on")


@pytest.mark.parametrize("kind, value, fast", [(k, v, f) for k, (_, table) in SWITCHES.items()
                                               for v, f in table.items()])
def test_the_environment_picks_the_path_at_load(kind, value, fast):
    var = SWITCHES[kind][0]
    env = {k: v for k, v in os.environ.items() if k != var}
    if value is not None:
        env[var] = value
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    code = f"from cobgs.render.ops import {kind}_fast_path_on; print({kind}_fast_path_on())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(fast)


@pytest.mark.parametrize("kind", sorted(SWITCHES))
def test_the_block_switches_and_restores(kind):
    switch, is_on = _switch(kind)
    before = is_on()
    with switch(not before):
        assert is_on() is (not before)
        with switch(before):
            assert is_on() is before
        assert is_on() is (not before)
    assert is_on() is before
    with pytest.raises(RuntimeError):
        with switch(not before):
            raise RuntimeError("inside")
    assert is_on() is before
