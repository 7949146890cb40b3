"""Just-in-time build of the native rasterizer (``csrc/``) into a per-user cache.

``load_extension()`` compiles the C++ sources with ``torch.utils.cpp_extension`` on
first use and loads the library, which registers the ``torch.ops.cobgs.*`` ops.

* **Cache folder:** ``$COBGS_EXT_DIR`` if set, else ``$XDG_CACHE_HOME/cobgs/ext`` (default
  ``~/.cache/cobgs/ext``). One sub-folder per build key.
* **Build key:** sha256 of every source and header under ``csrc/`` (path and content),
  the compiler flags, the torch version, the Python version, the machine architecture,
  the compiler's identity (``$CXX`` or ``c++``: resolved path and ``--version`` line; and
  ``$COBGS_CXX``'s) and the CUDA plan (below; with ``$CC``, nvcc's host compiler). Any source
  or compiler change therefore builds afresh. No
  ``-march=native`` is used, so a cached build runs on any CPU of the same architecture
  (which is why the CPU model is not part of the key).
* **CUDA:** the ``*_cuda.cu`` kernels are compiled into the same library only when torch
  has CUDA, an ``nvcc`` of the same major version as torch's CUDA is found
  (``$CUDA_HOME/bin/nvcc``, else ``nvcc`` on the PATH) and the target architectures are
  known: ``$TORCH_CUDA_ARCH_LIST`` (e.g. ``"9.0"`` or ``"8.6;9.0"``), else those of the
  visible GPUs. ``$COBGS_CUDA`` = ``0`` builds the CPU kernels only; ``1`` makes a missing
  piece an error instead of a CPU-only build. ``$MAX_JOBS`` caps the parallel compiler
  jobs (torch's own setting). :func:`cuda_plan` says what was decided and why.
* **Concurrency:** several processes may call this at once (pytest workers, other
  sessions). The build runs under an exclusive ``flock`` on ``<key>.lock`` (released by
  the OS if a process dies), in a private temporary folder that is renamed into place
  only when complete, so nobody ever loads a half-written library.
* **Failures:** the compiler runs in a child process; its complete output is attached to
  the :class:`~cobgs.errors.BuildError`. ``import cobgs`` never needs the extension;
  ``cobgs.rasterize(..., backend="reference")`` works without one.
* **A C++ error must be a Python error** (:mod:`cobgs.render.toolchain`). After linking,
  the library's dynamic section is read: a compiler that linked libstdc++ statically (the
  library would crash or lose the numbers of its messages on its first error) is replaced
  once by one that links it dynamically (``$COBGS_CXX``, else ``c++`` / ``g++`` on the PATH),
  saying so in one line; with none, the build fails naming ``$CXX``, its version and the fix.
  Then the library is loaded in a child process and its ``error_probe`` op called: it must
  raise a ``RuntimeError`` holding its numbers, or the build fails. The result is kept as
  ``probe.json`` beside the library; a cached library without one (built before these
  checks) is probed once on first load and rebuilt if it fails.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

from cobgs.errors import BuildError

# A source checkout (editable install) builds from the repository's csrc/; an installed
# wheel carries the same files as package data in cobgs/_csrc (a link to csrc/ in the
# repository).
_REPO_CSRC = Path(__file__).resolve().parents[2] / "csrc"
CSRC = _REPO_CSRC if _REPO_CSRC.is_dir() else Path(__file__).resolve().parents[1] / "_csrc"
# -O3 with auto-vectorisation of the per-row pixel loops, which needs
# -fno-trapping-math (lets GCC if-convert float compares; results are unchanged in the
# default floating-point environment). -ffp-contract=off keeps a*b+c unfused so scalar
# and SIMD code, forward and backward, round every per-pixel value identically.
# -fno-math-errno lets sqrt/floor inline. No -march=native (see the module docstring).
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math"]
LDFLAGS = ["-fopenmp"]
# nvcc: --fmad=false keeps a*b+c unfused, as -ffp-contract=off on the host, so the CUDA
# kernels evaluate the shared formulas (csrc/common/gs_math.h, sh_math.h) with the same
# roundings as the CPU kernels (identical pixel decisions and label counts);
# --expt-relaxed-constexpr lets device code call the constexpr std helpers they use.
CUDA_FLAGS = ["-O3", "--fmad=false", "--expt-relaxed-constexpr", "-lineinfo"]


def cflags() -> List[str]:
    """CFLAGS, plus -DCOBGS_PROFILE when $COBGS_PROFILE is set (phase timers and pair
    counters printed at exit, csrc/common/prof_cpu.h; a separate cached build)."""
    flag = os.environ.get("COBGS_PROFILE", "")
    return CFLAGS + (["-DCOBGS_PROFILE"] if flag not in ("", "0") else [])

_lock = threading.Lock()
_loaded: Optional[str] = None


def cache_root() -> Path:
    """The folder holding every cached build."""
    env = os.environ.get("COBGS_EXT_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "cobgs" / "ext"


def _source_files() -> List[Path]:
    if not CSRC.is_dir():
        raise BuildError(f"the C++ sources of the native rasterizer were not found at {CSRC} "
                         f"(a source checkout builds from csrc/, an installed wheel from cobgs/_csrc; "
                         f"reinstall cobgs); "
                         f"use backend=\"reference\" to render without them")
    return sorted(p for p in CSRC.rglob("*") if p.suffix in (".cpp", ".h", ".cu", ".cuh"))


_TRUE = ("1", "on", "yes", "true", "required")
_FALSE = ("0", "off", "no", "false")


def cuda_home() -> Optional[Path]:
    """The CUDA toolkit folder: $CUDA_HOME / $CUDA_PATH, else the one holding the nvcc on
    the PATH (its real location; a wrapper script on the PATH is looked through to
    /usr/local/cuda), else /usr/local/cuda. None when none holds bin/nvcc and
    include/cuda_runtime.h."""
    candidates = [os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH")]
    found = shutil.which("nvcc")
    if found:
        candidates.append(str(Path(found).resolve().parents[1]))
    candidates.append("/usr/local/cuda")
    for c in candidates:
        if c and (Path(c) / "bin" / "nvcc").is_file() and \
                (Path(c) / "include" / "cuda_runtime.h").is_file():
            return Path(c)
    return None


def nvcc_version(nvcc: str) -> Optional[str]:
    try:
        out = subprocess.run([nvcc, "--version"], capture_output=True, text=True,
                             timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    for line in out.splitlines():
        if "release" in line:  # "Cuda compilation tools, release 13.0, V13.0.88"
            return line.split("release", 1)[1].split(",")[0].strip()
    return None


def _visible_archs() -> str:
    import torch

    try:
        if not torch.cuda.is_available():
            return ""
        caps = {torch.cuda.get_device_capability(i) for i in range(torch.cuda.device_count())}
    except Exception:  # a broken driver: no GPU to build for
        return ""
    return ";".join(f"{major}.{minor}" for major, minor in sorted(caps))


_plan_cache: dict = {}


def cuda_plan() -> dict:
    """Whether this build includes the CUDA kernels, and with what.

    Returns ``{"enabled": True, "nvcc": path, "nvcc_version": "13.0", "arch": "9.0",
    "flags": [...]}`` or ``{"enabled": False, "reason": "..."}``.

    Raises:
        BuildError: ``$COBGS_CUDA=1`` and a piece is missing.
    """
    import torch

    mode = os.environ.get("COBGS_CUDA", "auto").strip().lower()
    env_key = (mode, *(os.environ.get(k, "") for k in ("TORCH_CUDA_ARCH_LIST", "CUDA_HOME",
                                                        "CUDA_PATH", "PATH")))
    if env_key in _plan_cache:
        return _plan_cache[env_key]
    reason = None
    plan: dict = {"enabled": False}
    if mode in _FALSE:
        reason = "disabled by COBGS_CUDA=0"
    elif torch.version.cuda is None:
        reason = f"this torch ({torch.__version__}) is built without CUDA"
    else:
        home = cuda_home()
        nvcc = str(home / "bin" / "nvcc") if home else None
        version = nvcc_version(nvcc) if nvcc else None
        arch = os.environ.get("TORCH_CUDA_ARCH_LIST", "").strip() or _visible_archs()
        if nvcc is None:
            reason = (f"no CUDA toolkit found (torch is built with CUDA {torch.version.cuda}; "
                      f"install the toolkit of that major version, or set CUDA_HOME to it)")
        elif version is None or version.split(".")[0] != torch.version.cuda.split(".")[0]:
            reason = (f"{nvcc} is CUDA {version or 'of unknown version'}, torch is built with "
                      f"CUDA {torch.version.cuda} (the major versions must match)")
        elif not arch:
            reason = ("no CUDA device is visible and TORCH_CUDA_ARCH_LIST is not set "
                      "(e.g. TORCH_CUDA_ARCH_LIST=9.0 for an H100)")
        else:
            plan = {"enabled": True, "nvcc": nvcc, "cuda_home": str(home),
                    "nvcc_version": version, "arch": arch, "flags": CUDA_FLAGS}
    if reason is not None:
        if mode in _TRUE:
            raise BuildError(f"COBGS_CUDA={mode} asks for the CUDA kernels, but {reason}")
        plan["reason"] = reason
    _plan_cache[env_key] = plan
    return plan


def build_key() -> str:
    """Hex digest identifying one build of the current sources and toolchain."""
    import torch

    plan = cuda_plan()
    h = hashlib.sha256()
    for path in _source_files():
        h.update(str(path.relative_to(CSRC)).encode() + b"\0" + path.read_bytes() + b"\0")
    h.update(json.dumps({
        "cflags": cflags(), "ldflags": LDFLAGS, "torch": torch.__version__,
        "python": list(sys.version_info[:2]), "machine": platform.machine(),
        "cxx": _compiler_key(),
        # $CC is nvcc's host compiler (torch passes it as -ccbin).
        "cuda": dict({k: plan[k] for k in ("nvcc_version", "arch", "flags")},
                     host_cc=os.environ.get("CC", "")) if plan["enabled"] else None,
    }, sort_keys=True).encode())
    return h.hexdigest()


def _compiler_key() -> dict:
    from .toolchain import compiler_identity

    cxx = compiler_identity()
    key = {"name": cxx.name, "path": cxx.path, "version": cxx.version}
    if os.environ.get("COBGS_CXX"):
        alt = compiler_identity(os.environ["COBGS_CXX"])
        key["cobgs_cxx"] = {"path": alt.path, "version": alt.version}
    return key


def extension_name() -> str:
    return f"cobgs_ext_{build_key()[:16]}"


@contextmanager
def _file_lock(path: Path, verbose: bool):
    with open(path, "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"cobgs: waiting for another process building the native extension "
                  f"(lock {path})", file=sys.stderr, flush=True)
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _check_toolchain(cxx: Optional[str] = None) -> None:
    cxx = cxx or os.environ.get("CXX") or "c++"
    if shutil.which(cxx) is None:
        raise BuildError(f"no C++ compiler found (looked for {cxx!r}; set $CXX or install "
                         f"g++) — needed to build the native rasterizer; "
                         f"backend=\"reference\" works without it")
    if shutil.which("ninja") is None and not _ninja_in_env():
        raise BuildError("the 'ninja' build tool was not found (pip install ninja) — needed "
                         "to build the native rasterizer")


def _ninja_in_env() -> bool:
    return Path(sys.executable).with_name("ninja").exists()


_CHILD = """
import sys, json
from torch.utils.cpp_extension import load
a = json.loads(sys.argv[1])
load(name=a["name"], sources=a["sources"], build_directory=a["build_dir"],
     extra_cflags=a["cflags"], extra_ldflags=a["ldflags"],
     extra_cuda_cflags=a["cuda_cflags"], verbose=True, is_python_module=False)
"""


@dataclass(frozen=True)
class BuildSpec:
    """What one library is built from: sources, flags, CUDA plan, and the namespace of its
    ``error_probe`` op. :func:`load_extension` builds the rasterizer's; tests build small ones
    through the same checks."""

    sources: tuple[str, ...]
    cflags: tuple[str, ...]
    ldflags: tuple[str, ...]
    cuda: dict = field(default_factory=lambda: {"enabled": False, "reason": "not asked for"})
    namespace: str = "cobgs"


def _rasterizer_spec() -> BuildSpec:
    plan = cuda_plan()
    suffixes = (".cpp", ".cu") if plan["enabled"] else (".cpp",)
    return BuildSpec(tuple(str(p) for p in _source_files() if p.suffix in suffixes), tuple(cflags()),
                     tuple(LDFLAGS), plan)


def _compile(name: str, root: Path, final: Path, verbose: bool, spec: BuildSpec,
             cxx: Optional[str] = None) -> None:
    """Compile ``spec`` into ``final/<name>.so`` (a private folder renamed into place), with
    ``cxx`` as the compiler where given (else ``$CXX``, as torch's build does)."""
    _check_toolchain(cxx)
    for stale in root.glob(f"{name}.build-*"):  # left by a crashed build (we hold the lock)
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{name}.build-", dir=root))
    plan = spec.cuda
    args = json.dumps({"name": name, "sources": list(spec.sources), "build_dir": str(tmp),
                       "cflags": list(spec.cflags), "ldflags": list(spec.ldflags),
                       "cuda_cflags": plan.get("flags", [])})
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    if cxx:
        env["CXX"] = cxx
    if plan["enabled"]:
        env["CUDA_HOME"] = plan["cuda_home"]
        env["TORCH_CUDA_ARCH_LIST"] = plan["arch"]
    if verbose:
        what = (f"CPU + CUDA kernels for {plan['arch']}" if plan["enabled"]
                else f"CPU kernels only ({plan['reason']})")
        print(f"cobgs: building {name} in {tmp}: {what}", file=sys.stderr, flush=True)
    proc = subprocess.run([sys.executable, "-c", _CHILD, args], stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, env=env, text=True)
    if verbose:
        print(proc.stdout, file=sys.stderr, flush=True)
    so = tmp / f"{name}.so"
    if proc.returncode != 0 or not so.is_file():
        shutil.rmtree(tmp, ignore_errors=True)
        raise BuildError(f"building the native rasterizer failed (exit code "
                         f"{proc.returncode}); full compiler log follows. "
                         f"backend=\"reference\" renders without the extension.\n"
                         f"{proc.stdout}")
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)


PROBE_FILE = "probe.json"


def _build_checked(name: str, root: Path, final: Path, verbose: bool, spec: BuildSpec) -> None:
    """:func:`_compile`, then the two checks of the module docstring: a statically linked
    libstdc++ is rebuilt once with a compiler that links it dynamically; the error probe
    must pass. Writes ``probe.json`` (what was built with what, and the probe) beside the
    library; a library failing either check is removed and :class:`BuildError` raised."""
    from .toolchain import compiler_identity, dynamic_compiler, links_libstdcxx_statically, probe_library, \
        static_message

    so = final / f"{name}.so"
    cxx = compiler_identity()
    chosen = os.environ.get("COBGS_CXX")
    if chosen and shutil.which(chosen) is None:  # said now, not after a whole build
        raise BuildError(f"COBGS_CXX={chosen}: no such compiler (not found on the PATH, or not executable); "
                         "unset it or name a C++ compiler that links libstdc++ dynamically, e.g. g++")
    _compile(name, root, final, verbose, spec)
    used, switched = cxx, None
    if links_libstdcxx_statically(so):
        alt = dynamic_compiler(cxx)
        if alt is None:
            shutil.rmtree(final, ignore_errors=True)
            raise BuildError(static_message(cxx, "its library does not need libstdc++.so.6"))
        print(f"cobgs: {cxx} links libstdc++ statically, which breaks C++ errors in a torch extension; "
              f"building again with {alt}", file=sys.stderr, flush=True)
        _compile(name, root, final, verbose, spec, cxx=alt.path)
        if links_libstdcxx_statically(so):
            shutil.rmtree(final, ignore_errors=True)
            raise BuildError(static_message(cxx, f"and so does {alt}"))
        used, switched = alt, str(cxx)
    probe = probe_library(so, spec.namespace)
    if not probe.ok:
        shutil.rmtree(final, ignore_errors=True)
        raise BuildError(f"the native extension built with {used} fails the error probe: {probe.detail}. "
                         f"A C++ error of this library would not reach Python intact. Fix: build with "
                         f"another compiler, e.g. `CXX=g++ cobgs build` (or set COBGS_CXX)")
    _write_probe(final, {"compiler": str(used), "compiler_path": used.path, "compiler_version": used.version,
                         "switched_from": switched, "libstdcxx": "dynamic", "probe": probe.to_json()})


def _write_probe(final: Path, record: dict) -> None:
    """Write ``probe.json`` beside the library, with the library's size and sha256 (what a
    later load checks before mapping it: a truncated library would kill the process with
    SIGBUS, not raise)."""
    so = next(iter(sorted(final.glob("*.so"))), None)
    if so is not None:
        record = {**record, "library": so.name, "library_bytes": so.stat().st_size, "library_sha256": _sha256(so)}
    tmp = final / f".{PROBE_FILE}.tmp"
    tmp.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, final / PROBE_FILE)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_probe(final: Path) -> Optional[dict]:
    """The ``probe.json`` a checked build left beside its library, or None."""
    try:
        rec = json.loads((Path(final) / PROBE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None


def library_problem(so: Path) -> str:
    """Why the cached library ``so`` must not be loaded into this process ("" when it may): no
    probe.json (never checked), or a library whose size or sha256 is not the one recorded when
    it was built and probed (truncated, replaced). Such a library is probed in a child process
    or rebuilt, never mapped here."""
    probe_path = so.parent / PROBE_FILE
    if probe_path.exists() and not probe_path.is_file():
        return f"{probe_path} is not a file"
    rec = read_probe(so.parent)
    if rec is None:
        return "it has no probe.json (built before the checks, or damaged)"
    if not isinstance(rec.get("library_sha256"), str):
        return "its probe.json records no size and hash (written before they were kept)"
    try:
        size = so.stat().st_size
    except OSError as exc:
        return f"cannot read it ({exc.strerror})"
    if size != rec.get("library_bytes"):
        return f"it is {size} bytes, not the {rec.get('library_bytes')} recorded when it was built (truncated?)"
    if _sha256(so) != rec["library_sha256"]:
        return "its content is not what was built (its sha256 differs from probe.json's)"
    return ""


def ensure_library(name: str, root: Path, spec: BuildSpec, verbose: bool = False, force: bool = False) -> Path:
    """The checked library ``root/name/name.so``: built (and checked) if missing or
    ``force``; a cached one whose probe.json does not vouch for it (never checked, or its size
    or hash changed) is probed once in a child process and rebuilt if it fails. A library that
    passes needs no lock, so a read-only extension cache holding one serves it; anything else
    runs under the build's file lock."""
    final = root / name
    so = final / f"{name}.so"
    if not force and so.is_file() and not library_problem(so):
        return so
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BuildError(f"cannot create the extension cache folder {root}: {exc} "
                         f"(set COBGS_EXT_DIR to a writable folder)") from exc
    try:
        lock = _file_lock(root / f"{name}.lock", verbose)
        lock.__enter__()
    except OSError as exc:
        why = library_problem(so) if so.is_file() else "it holds no build of this version"
        raise BuildError(f"the extension cache {root} cannot be written ({exc.strerror}) and its library cannot be "
                         f"used as it is: {why}. Set COBGS_EXT_DIR to a writable folder (or run `cobgs build` where "
                         "this one is writable)") from None
    try:
        problem = "" if force or not so.is_file() else library_problem(so)
        if force or not so.is_file() or (final / PROBE_FILE).exists() and not (final / PROBE_FILE).is_file():
            _build_checked(name, root, final, verbose, spec)
        elif problem:
            from .toolchain import probe_library

            probe = probe_library(so, spec.namespace)  # (in a child process: a bad library cannot kill us)
            old = read_probe(final)
            if probe.ok and old is not None and "library_sha256" not in (old or {}):
                _write_probe(final, {**old, "probe": probe.to_json()})  # a checked build of before: hash kept now
            elif probe.ok and old is None:
                _write_probe(final, {"compiler": None, "libstdcxx": "not checked (built before the checks)",
                                     "probe": probe.to_json()})
            else:
                print(f"cobgs: the cached native extension {so} "
                      + (f"fails the error probe ({probe.detail}; {problem})" if not probe.ok
                         else f"cannot be used ({problem})") + "; rebuilding it", file=sys.stderr, flush=True)
                _build_checked(name, root, final, verbose, spec)
    finally:
        lock.__exit__(None, None, None)
    return so


def has_cuda_kernels() -> bool:
    """Whether the loaded extension registered CUDA kernels (loads it if needed)."""
    load_extension()
    import torch

    return torch._C._dispatch_has_kernel_for_dispatch_key("cobgs::blend", "CUDA")


def load_extension(verbose: bool = False, force: bool = False) -> str:
    """Build (if needed) and load the native ops; returns the library path.

    Args:
        verbose: print the build folder and the full compiler output.
        force: rebuild even if a cached build exists. (A library already loaded in this
            process stays loaded; the rebuilt one is used by new processes.)

    Raises:
        BuildError: no compiler/ninja, compilation failed (message holds the full log), or
            the library fails the checks of the module docstring.
    """
    global _loaded
    with _lock:
        if _loaded is not None and not force:
            return _loaded
        name = extension_name()
        so = ensure_library(name, cache_root(), _rasterizer_spec(), verbose, force)
        if _loaded is None:
            import torch

            try:
                torch.ops.load_library(str(so))
            except OSError as exc:
                raise BuildError(f"the cached native extension {so} could not be loaded: "
                                 f"{exc}; delete {so.parent} to rebuild it") from exc
            _loaded = str(so)
        return str(so)
