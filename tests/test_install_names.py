"""The top-level packages installed beside cobgs (docs/install_names.md): the command line
refuses to run with another distribution's `pipeline`, `stages` or `reports` first on the path."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_siblings_are_ours_here():
    from stages.commands.cli import check_sibling_packages

    assert check_sibling_packages() is None


def test_another_reports_package_first_on_the_path_is_named(tmp_path):
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "__init__.py").write_text("# someone else's reports package\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))
    r = subprocess.run([sys.executable, "-c", "import sys; from stages.commands.cli import main; sys.exit(main(['--help']))"],
                       env=env, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"the package 'reports' imported here is {tmp_path / 'reports' / '__init__.py'}" in r.stderr, r.stderr
    assert "docs/install_names.md" in r.stderr
