"""A C++ error must be a Python error, whatever compiler builds the extension (issue 46).

Small one-op libraries go through the same checked build as the rasterizer
(``cobgs.render.build.ensure_library``): a compiler wrapper that links libstdc++ statically
(``g++ -static-libstdc++``, as a cluster's portable-binary wrapper does) must be replaced by
one that links it dynamically, or the build must fail saying how to fix it; the error probe
must catch a library whose error path drops the numbers (g++ 12 with -static-libstdc++ here)
or crashes; a cached library that fails the probe is rebuilt. Each library builds in ~10 s.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from cobgs.errors import BuildError
from cobgs.render import build
from cobgs.render.toolchain import links_libstdcxx_statically, needed_libraries, probe_library

REPO = Path(__file__).resolve().parents[2]
GXX = shutil.which("g++")
pytestmark = pytest.mark.skipif(GXX is None, reason="needs g++ to build the test libraries")

PROBE_CPP = r"""
#include <torch/library.h>
#include <cstdint>
#include <cstdlib>
namespace {
int64_t error_probe(int64_t n) {
  %s
  TORCH_CHECK(n == 0, "cobgs error probe: ", n, " ", 2.5, " ", -7);
  return n;
}
}
TORCH_LIBRARY(%s, m) { m.def("error_probe(int n) -> int", &error_probe); }
"""


def _spec(tmp: Path, namespace: str, abort: bool = False, ldflags=()) -> build.BuildSpec:
    src = tmp / f"{namespace}.cpp"
    src.write_text(PROBE_CPP % ("if (n != 0) std::abort();" if abort else "", namespace))
    return build.BuildSpec((str(src),), ("-O0",), tuple(ldflags), namespace=namespace)


def _static_wrapper(folder: Path) -> Path:
    """A compiler that links libstdc++ statically: what a portable-binary toolchain does."""
    folder.mkdir(parents=True, exist_ok=True)
    script = folder / "static-g++"
    tools = os.path.dirname(os.path.realpath(GXX))  # where g++ finds as / ld, whatever PATH the caller has
    script.write_text(f'#!/bin/sh\nPATH="{tools}:$PATH" exec {GXX} -static-libstdc++ "$@"\n')
    script.chmod(script.stat().st_mode | stat.S_IXUSR)
    return script


@pytest.fixture(scope="module")
def libs(tmp_path_factory):
    """Three libraries built without the checks: dynamic, static libstdc++, aborting."""
    root = tmp_path_factory.mktemp("libs")
    out = {}
    for name, kw in (("good", {}), ("static", {"ldflags": ("-static-libstdc++",)}), ("aborts", {"abort": True})):
        ns = f"cobgs_t_{name}"
        build._compile(ns, root, root / ns, False, _spec(root, ns, **kw))
        out[name] = root / ns / f"{ns}.so"
    return out


def test_the_elf_reader_sees_how_libstdcxx_was_linked(libs):
    needed = needed_libraries(libs["good"])
    assert "libstdc++.so.6" in needed and "libc.so.6" in needed
    assert not links_libstdcxx_statically(libs["good"]) and links_libstdcxx_statically(libs["static"])
    if shutil.which("readelf"):
        out = subprocess.run(["readelf", "-d", str(libs["static"])], capture_output=True, text=True).stdout
        assert [ln.split("[")[1].rstrip("]") for ln in out.splitlines() if "(NEEDED)" in ln] == \
            needed_libraries(libs["static"])
    with pytest.raises(ValueError, match="not an ELF file"):
        needed_libraries(Path(__file__))


def test_the_probe_catches_lost_numbers_and_a_crash(libs):
    ok = probe_library(libs["good"], "cobgs_t_good")
    assert ok.ok and ok.message == "cobgs error probe: 12345 2.5 -7"
    lost = probe_library(libs["static"], "cobgs_t_static")  # g++ 12 + -static-libstdc++: numbers dropped
    assert not lost.ok and "lost its numbers" in lost.detail and "12345" not in lost.message, lost
    crash = probe_library(libs["aborts"], "cobgs_t_aborts")
    assert not crash.ok and "died of SIGABRT" in crash.detail, crash


def test_a_static_compiler_is_replaced_saying_so(tmp_path, monkeypatch, capfd):
    fake = _static_wrapper(tmp_path / "bin")
    monkeypatch.setenv("CXX", str(fake))
    monkeypatch.delenv("COBGS_CXX", raising=False)
    so = build.ensure_library("cobgs_t_switch", tmp_path / "cache", _spec(tmp_path, "cobgs_t_switch"))
    err = capfd.readouterr().err
    assert f"{fake}" in err and "links libstdc++ statically" in err and "building again with c++" in err, err
    assert not links_libstdcxx_statically(so)
    rec = build.read_probe(so.parent)
    assert rec["probe"]["ok"] and str(fake) in rec["switched_from"] and rec["libstdcxx"] == "dynamic"


def test_without_another_compiler_the_build_fails_with_the_fix(tmp_path, monkeypatch):
    fake = _static_wrapper(tmp_path / "bin")
    for name in ("c++", "g++"):  # every compiler on the PATH is the static one
        os.symlink(fake, tmp_path / "bin" / name)
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{Path(sys.executable).parent}")
    monkeypatch.setenv("CXX", str(fake))
    monkeypatch.delenv("COBGS_CXX", raising=False)
    with pytest.raises(BuildError) as err:
        build.ensure_library("cobgs_t_nofix", tmp_path / "cache", _spec(tmp_path, "cobgs_t_nofix"))
    msg = str(err.value)
    assert f"$CXX = {fake}" in msg and "links libstdc++ statically" in msg and "CXX=g++ cobgs build" in msg
    version = subprocess.run([GXX, "--version"], capture_output=True, text=True).stdout.splitlines()[0]
    assert version in msg  # its --version line
    assert not list((tmp_path / "cache").rglob("*.so"))  # nothing left that a later run would load


def test_a_cached_library_that_fails_the_probe_is_rebuilt(libs, tmp_path, capfd):
    """A library in the extension cache built before the checks (no probe.json): probed once
    on first load; one whose numbers vanish is rebuilt, one that passes is kept."""
    root = tmp_path / "cache"
    name = "cobgs_t_static"
    (root / name).mkdir(parents=True)
    shutil.copy(libs["static"], root / name / f"{name}.so")
    so = build.ensure_library(name, root, _spec(tmp_path, name))
    err = capfd.readouterr().err
    assert "fails the error probe" in err and "rebuilding it" in err, err
    assert not links_libstdcxx_statically(so) and build.read_probe(root / name)["probe"]["ok"]
    good = "cobgs_t_good"
    (root / good).mkdir()
    shutil.copy(libs["good"], root / good / f"{good}.so")
    before = (root / good / f"{good}.so").stat().st_mtime_ns
    build.ensure_library(good, root, _spec(tmp_path, good))
    assert (root / good / f"{good}.so").stat().st_mtime_ns == before  # passed: kept, not rebuilt
    assert build.read_probe(root / good)["probe"]["ok"]


def test_a_damaged_or_read_only_extension_cache_never_kills_the_process(libs, tmp_path, monkeypatch, capfd):
    """Issue 56 M4 / M5 / M15: a truncated cached library was mapped and killed the process
    with SIGBUS (probe.json vouched for it); a read-only cache holding a valid, probed build
    could not be used (``[Errno 30]`` on the lock file); a probe.json that is a folder was a
    traceback. probe.json now records the library's size and sha256: a library that matches
    is served without the lock, anything else is probed in a child process or rebuilt, and an
    unwritable cache that cannot serve says so in one line."""
    import errno

    root = tmp_path / "cache"
    name = "cobgs_t_good"
    (root / name).mkdir(parents=True)
    so = root / name / f"{name}.so"
    shutil.copy(libs["good"], so)
    build.ensure_library(name, root, _spec(tmp_path, name))  # probed in a child, size and hash recorded
    rec = build.read_probe(root / name)
    assert rec["library_bytes"] == so.stat().st_size and len(rec["library_sha256"]) == 64
    assert build.library_problem(so) == ""

    def read_only(path, verbose):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(build, "_file_lock", read_only)
    assert build.ensure_library(name, root, _spec(tmp_path, name)) == so  # M5: served as it is
    data = so.read_bytes()
    so.write_bytes(data[: len(data) // 2])  # M4: truncated after the build was checked
    assert "truncated" in build.library_problem(so)
    with pytest.raises(BuildError, match=r"cannot be written \(Read-only file system\) and its library cannot be "
                                         r"used as it is: it is \d+ bytes, not the \d+ recorded"):
        build.ensure_library(name, root, _spec(tmp_path, name))
    so.write_bytes(data)
    (root / name / "probe.json").unlink()
    (root / name / "probe.json").mkdir()  # M15: a folder where the record should be
    with pytest.raises(BuildError, match="probe.json is not a file"):
        build.ensure_library(name, root, _spec(tmp_path, name))
    monkeypatch.undo()
    shutil.rmtree(root / name / "probe.json")
    build._write_probe(root / name, {"probe": {"ok": True}})  # a record of the whole library ...
    so.write_bytes(data[: len(data) // 2])  # ... which is then cut short: rebuilt, never mapped here
    out = build.ensure_library(name, root, _spec(tmp_path, name))
    err = capfd.readouterr().err
    assert "truncated?" in err and "rebuilding it" in err and build.library_problem(out) == ""
    assert probe_library(out, name).ok


def test_cobgs_cxx_that_does_not_exist_is_said_before_the_build(tmp_path, monkeypatch):
    """Issue 56 (low): ``COBGS_CXX=/nonexistent`` was reported as "no other compiler found"
    after a whole build."""
    monkeypatch.setenv("COBGS_CXX", "/nonexistent/g++")
    t0 = __import__("time").perf_counter()
    with pytest.raises(BuildError, match=r"COBGS_CXX=/nonexistent/g\+\+: no such compiler"):
        build.ensure_library("cobgs_t_nocxx", tmp_path / "cache", _spec(tmp_path, "cobgs_t_nocxx"))
    assert __import__("time").perf_counter() - t0 < 5 and not list((tmp_path / "cache").rglob("*.so"))


def test_the_compiler_enters_the_build_key(monkeypatch, tmp_path):
    real = build.build_key()
    fake = _static_wrapper(tmp_path / "bin")
    monkeypatch.setenv("CXX", str(fake))
    assert build.build_key() != real
    monkeypatch.delenv("CXX")
    monkeypatch.setenv("COBGS_CXX", GXX)
    assert build.build_key() != real


def test_the_rasterizer_extension_passes_its_own_probe():
    so = Path(build.load_extension())
    rec = build.read_probe(so.parent)
    assert rec is not None and rec["probe"]["ok"], rec
    assert probe_library(so).ok
    import torch

    with pytest.raises(RuntimeError, match="cobgs error probe: 3 2.5 -7"):
        torch.ops.cobgs.error_probe(3)
