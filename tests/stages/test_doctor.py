"""`cobgs doctor` on this machine (CPU): what it prints, its JSON record, and its exit code
when a check fails (issue 46)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_doctor_on_the_cpu_prints_and_records_every_check(tmp_path):
    out = tmp_path / "doctor.json"
    proc = subprocess.run([sys.executable, "-m", "stages.commands.cli", "doctor", "--json", str(out)],
                          capture_output=True, text=True, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    text = proc.stdout
    for what in ("torch ", "compiler ", "nvcc ", "extension ", "error probe ok", "render cpu  ok",
                 "timing cpu  100000 Gaussians at 504x378, forward + backward", "all checks passed"):
        assert what in text, (what, text)
    rec = json.loads(out.read_text())
    assert rec["ok"] is True and rec["torch"] and rec["compiler"]["path"]
    assert rec["extension"]["path"].endswith(".so") and rec["extension"]["libstdcxx"] in ("dynamic", None) or \
        "not checked" in rec["extension"]["libstdcxx"]
    assert rec["checks"]["error_probe"]["message"] == "cobgs error probe: 12345 2.5 -7"
    cpu = rec["checks"]["render_cpu"]
    assert cpu["ok"] and cpu["image_max_abs"] <= 1e-4 and cpu["radii_equal"]
    assert set(cpu["grad_max_rel"]) == {"means", "quats", "scales", "opacities", "features", "background"}
    assert rec["timing"]["cpu"]["fwd_bwd_ms"] > 0 and rec["timing"]["cpu"]["n"] == 100_000
    only = subprocess.run([sys.executable, "-m", "stages.commands.cli", "doctor", "--json", "-", "--no-timing"],
                          capture_output=True, text=True, cwd=REPO, timeout=600)
    assert only.returncode == 0 and json.loads(only.stdout)["checks"]["render_cpu"]["ok"]


def test_doctor_exits_non_zero_when_a_check_fails(monkeypatch, capsys):
    import cobgs.render.selfcheck as sc
    from stages.commands.cli import main

    real = sc.parity

    def broken(device="cpu", **kw):
        r = real(device, **kw)
        r.ok, r.image_max_abs = False, 0.5
        return r

    monkeypatch.setattr(sc, "parity", broken)
    assert main(["doctor", "--no-timing"]) == 1
    out = capsys.readouterr().out
    assert "render cpu  FAILED" in out and "result      FAILED: render_cpu" in out


def test_doctor_says_a_bad_json_path_first_and_prints_json_when_the_extension_is_unusable(monkeypatch, capsys,
                                                                                          tmp_path):
    """Issue 56 M5 / M15: ``doctor --json /nonexistent/x.json`` was a traceback after every
    check had run; with an extension cache it could not use, ``doctor --json -`` printed no
    JSON."""
    import errno
    import time

    from cobgs.render import build
    from stages.commands.cli import main

    t0 = time.perf_counter()
    assert main(["doctor", "--json", "/nonexistent/x.json"]) == 2
    assert "the folder /nonexistent does not exist" in capsys.readouterr().err
    assert time.perf_counter() - t0 < 10  # before the checks
    assert main(["doctor", "--json", str(tmp_path)]) == 2 and "is a folder" in capsys.readouterr().err

    def unusable(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system", "/ro/cache/cobgs_ext.lock")

    monkeypatch.setattr(build, "load_extension", unusable)
    assert main(["doctor", "--json", "-", "--no-timing"]) == 1
    rec = json.loads(capsys.readouterr().out)
    assert rec["ok"] is False and "Read-only file system" in rec["checks"]["extension"]["detail"]
