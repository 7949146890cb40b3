"""The library's runnable examples (``>>>`` in docstrings) run on the CPU as written."""

from __future__ import annotations

import doctest

import pytest

import cobgs.render.rasterize


@pytest.mark.parametrize("module", [cobgs.render.rasterize])
def test_docstring_examples_run(module):
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted >= 3 and result.failed == 0, result
