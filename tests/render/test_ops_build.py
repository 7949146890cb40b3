"""Building and loading the native extension (cobgs/render/build.py)."""

from __future__ import annotations

import fcntl
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cobgs.render import build
from cobgs.errors import BuildError

REPO = Path(__file__).resolve().parents[2]


def run_python(code: str, env_extra: dict, timeout=120) -> subprocess.CompletedProcess:
    env = dict(os.environ, **env_extra)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, cwd=REPO, timeout=timeout)


def test_import_and_reference_work_without_a_compiler(tmp_path):
    """No extension in the cache and no compiler: the package imports, the reference
    backend renders, and the native backend says what is missing."""
    code = """
import sys, torch
import cobgs
assert "cobgs.render.ops" not in sys.modules, "import cobgs must not load the extension"
args = (torch.zeros(1, 3) + torch.tensor([0., 0., 2.]), torch.tensor([[1., 0, 0, 0]]),
        torch.full((1, 3), 0.1), torch.tensor([0.5]), torch.ones(1, 3), torch.eye(4),
        torch.tensor([[10., 0, 4], [0, 10, 4], [0, 0, 1]]), 8, 8)
out = cobgs.rasterize(*args, backend="reference")
print("reference-ok", float(out.alpha.max()) > 0)
try:
    cobgs.rasterize(*args)
except cobgs.BuildError as exc:
    print("build-error:", exc)
"""
    proc = run_python(code, {"COBGS_EXT_DIR": str(tmp_path / "cache"),
                             "CXX": "/nonexistent/c++"})
    assert proc.returncode == 0, proc.stderr
    assert "reference-ok True" in proc.stdout
    assert "build-error: no C++ compiler found (looked for '/nonexistent/c++'" in proc.stdout
    assert 'backend="reference" works without it' in proc.stdout


def copy_sources(tmp_path: Path) -> Path:
    dst = tmp_path / "csrc"
    shutil.copytree(build.CSRC, dst)
    return dst


def test_build_key_follows_the_sources(tmp_path, monkeypatch):
    real = build.build_key()
    src = copy_sources(tmp_path)
    monkeypatch.setattr(build, "CSRC", src)
    assert build.build_key() == real  # depends on relative paths and contents only
    header = src / "common" / "gs_math.h"
    header.write_text(header.read_text() + "\n// changed\n")
    changed = build.build_key()
    assert changed != real
    (src / "extra_cpu.cpp").write_text("// new file\n")
    assert build.build_key() not in (real, changed)


def test_failed_build_shows_the_full_compiler_log(tmp_path, monkeypatch):
    src = tmp_path / "csrc"
    src.mkdir()
    (src / "broken_cpu.cpp").write_text('#error "cobgs-test: deliberately broken source"\n')
    monkeypatch.setattr(build, "CSRC", src)
    monkeypatch.setenv("COBGS_EXT_DIR", str(tmp_path / "cache"))
    with pytest.raises(BuildError) as info:
        build.load_extension(force=True)
    msg = str(info.value)
    assert "building the native rasterizer failed" in msg
    assert "cobgs-test: deliberately broken source" in msg  # the compiler's own message
    assert "broken_cpu.cpp" in msg and "-ffp-contract=off" in msg  # the command line
    # Nothing half-built is left where a later run would load it.
    assert not any(p.suffix == ".so" for p in (tmp_path / "cache").rglob("*"))


def test_second_process_waits_for_the_builder(tmp_path):
    """A process that must build or check the library and finds the build lock held waits
    (and says so), then loads. (A library whose probe.json vouches for it needs no lock: a
    copy without one, in a cache of its own, stands for a build in progress.)"""
    import os
    import shutil

    so = Path(build.load_extension())  # built and cached (make test builds it first)
    ext = tmp_path / "ext"
    shutil.copytree(so.parent, ext / so.parent.name)
    (ext / so.parent.name / "probe.json").unlink()
    lock = ext / f"{build.extension_name()}.lock"
    with open(lock, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        child = subprocess.Popen(
            [sys.executable, "-c", "from cobgs.render import build; print(build.load_extension())"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
            env={**os.environ, "COBGS_EXT_DIR": str(ext)})
        try:
            # Wait (at most 60 s) until the child reports that it is blocked on the lock.
            deadline = time.time() + 60
            seen = ""
            while "waiting for another process" not in seen and time.time() < deadline:
                ready, _, _ = select.select([child.stderr], [], [], deadline - time.time())
                if not ready:
                    break
                line = child.stderr.readline()
                if not line:
                    break
                seen += line
            assert "waiting for another process building the native extension" in seen, seen
            assert child.poll() is None  # still blocked while we hold the lock
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
    out, err = child.communicate(timeout=60)
    assert child.returncode == 0, err
    assert out.strip().endswith(".so")


def test_cli_build_reports_the_library():
    proc = subprocess.run([sys.executable, "-m", "stages.commands.cli", "build"], capture_output=True,
                          text=True, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "cobgs native extension ready:" in proc.stdout and ".so" in proc.stdout
    assert "CUDA kernels: " in proc.stdout  # built, or why not


def test_wheel_carries_the_sources_and_builds_from_them(tmp_path):
    """A non-editable install has no csrc/ beside the package: the wheel carries the C++
    sources as cobgs/_csrc and the JIT build finds them there, with the same build key
    (so the same cached extension) as the source checkout."""
    import zipfile

    wheel_dir = tmp_path / "wheel"
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps",
                    "--no-build-isolation", "-q", "-w", str(wheel_dir)],
                   check=True, capture_output=True, timeout=300)
    (wheel,) = wheel_dir.glob("cobgs-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    sources = [p.relative_to(build.CSRC).as_posix() for p in build._source_files()]
    assert sources and all(f"cobgs/_csrc/{s}" in names for s in sources)

    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    code = ("import cobgs.render.build as b; print(b.CSRC); print(b.build_key())")
    env = {**os.environ, "PYTHONPATH": str(site)}
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()
    assert out[0] == str((site / "cobgs" / "_csrc").resolve())
    assert out[1] == build.build_key()


def test_cuda_plan_says_why_the_cuda_kernels_are_left_out(monkeypatch):
    """On this CPU torch the plan is CPU-only with the reason; COBGS_CUDA=0 forces that,
    COBGS_CUDA=1 turns a missing piece into an error naming it."""
    import torch

    monkeypatch.setenv("COBGS_CUDA", "0")
    plan = build.cuda_plan()
    assert plan == {"enabled": False, "reason": "disabled by COBGS_CUDA=0"}
    monkeypatch.setenv("COBGS_CUDA", "auto")
    plan = build.cuda_plan()
    if torch.version.cuda is None:
        assert not plan["enabled"] and "built without CUDA" in plan["reason"]
        monkeypatch.setenv("COBGS_CUDA", "1")
        with pytest.raises(BuildError, match="COBGS_CUDA=1 asks for the CUDA kernels, but this "
                                             "torch .* is built without CUDA"):
            build.cuda_plan()


def test_cuda_plan_enters_the_build_key(monkeypatch):
    """A CUDA build and a CPU-only build of the same sources are different libraries."""
    monkeypatch.setattr(build, "cuda_plan", lambda: {"enabled": False, "reason": "x"})
    cpu_only = build.build_key()
    monkeypatch.setattr(build, "cuda_plan", lambda: {
        "enabled": True, "nvcc": "/x/nvcc", "cuda_home": "/x", "nvcc_version": "13.0",
        "arch": "9.0", "flags": build.CUDA_FLAGS})
    with_cuda = build.build_key()
    monkeypatch.setattr(build, "cuda_plan", lambda: {
        "enabled": True, "nvcc": "/x/nvcc", "cuda_home": "/x", "nvcc_version": "13.0",
        "arch": "8.6;9.0", "flags": build.CUDA_FLAGS})
    assert len({cpu_only, with_cuda, build.build_key()}) == 3


def test_cuda_home_is_found_through_a_wrapper_script(tmp_path, monkeypatch):
    """An nvcc on the PATH that is a wrapper script (not a link) does not mislead the
    toolkit search: CUDA_HOME, then the folder holding bin/nvcc and include/."""
    home = tmp_path / "cuda-13.0"
    (home / "bin").mkdir(parents=True)
    (home / "include").mkdir()
    (home / "bin" / "nvcc").write_text("#!/bin/sh\n")
    (home / "include" / "cuda_runtime.h").write_text("")
    wrapper = tmp_path / "wrap"
    wrapper.mkdir()
    (wrapper / "nvcc").write_text(f"#!/bin/sh\nexec {home}/bin/nvcc \"$@\"\n")
    (wrapper / "nvcc").chmod(0o755)
    monkeypatch.delenv("CUDA_PATH", raising=False)
    monkeypatch.setenv("CUDA_HOME", str(home))
    assert build.cuda_home() == home
    monkeypatch.delenv("CUDA_HOME")
    monkeypatch.setenv("PATH", str(wrapper))
    found = build.cuda_home()
    assert found != wrapper.parent  # never the wrapper's parent folder
    assert found is None or (found / "include" / "cuda_runtime.h").is_file()
