"""What the native extension was built with, and whether its C++ errors reach Python.

A C++ extension must share the process's C++ runtime. torch has already loaded the system's
``libstdc++.so.6``; a library that carries its own copy (a compiler wrapper that links
libstdc++ statically: cluster module systems, portable-binary toolchains, devtoolset-style
compilers) formats the message of every ``TORCH_CHECK`` with its own ``std::ostream`` and
hands it across the boundary to the other runtime. Seen: GCC 13.3 linking statically on
Ubuntu 24.04 crashed the process (SIGSEGV in ``std::basic_ostream::_M_insert<long>``) on the
first error that formats a number; GCC 12.2 with ``-static-libstdc++`` on Debian 12 drops
every number from the message silently (``"dim "`` for ``"dim 1"``). Everything that does not
raise works, so only an error path shows it.

This module gives the build its checks:

* :func:`needed_libraries` reads an ELF file's ``DT_NEEDED`` entries in pure Python;
  :func:`links_libstdcxx_statically` is true for a C++ library that does not need
  ``libstdc++.so.6``.
* :func:`compiler_identity`: the compiler's resolved path and ``--version`` line (part of the
  build key).
* :func:`dynamic_compiler`: a compiler to build with instead (``$COBGS_CXX``, else ``c++`` /
  ``g++`` on the PATH that are not the one that linked statically).
* :func:`probe_library`: loads a built library in a child process and calls its
  ``error_probe`` op, which must raise a ``RuntimeError`` holding its numbers; a crash or a
  message without them is a failed probe.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

#: The message the probe op raises (csrc/cobgs_ops.cpp) for ``PROBE_ARG``.
PROBE_ARG = 12345
PROBE_MESSAGE = f"cobgs error probe: {PROBE_ARG} 2.5 -7"
_DT_NEEDED, _DT_STRTAB, _DT_NULL = 1, 5, 0
_SHT_DYNAMIC = 6


def needed_libraries(path: os.PathLike | str) -> list[str]:
    """The ``DT_NEEDED`` entries of an ELF shared library (its dynamic section), in order.

    Raises:
        ValueError: not an ELF file, or no dynamic section.
    """
    data = Path(path).read_bytes()
    if data[:4] != b"\x7fELF":
        raise ValueError(f"{path}: not an ELF file")
    is64 = data[4] == 2
    end = "<" if data[5] == 1 else ">"
    if is64:
        shoff, = struct.unpack_from(end + "Q", data, 0x28)
        shentsize, shnum = struct.unpack_from(end + "HH", data, 0x3A)
    else:
        shoff, = struct.unpack_from(end + "I", data, 0x20)
        shentsize, shnum = struct.unpack_from(end + "HH", data, 0x2E)
    sections = []
    for i in range(shnum):
        off = shoff + i * shentsize
        if is64:
            _, sh_type, _, _, sh_offset, sh_size, sh_link = struct.unpack_from(end + "IIQQQQI", data, off)
        else:
            _, sh_type, _, _, sh_offset, sh_size, sh_link = struct.unpack_from(end + "IIIIIII", data, off)
        sections.append((sh_type, sh_offset, sh_size, sh_link))
    dyn = [s for s in sections if s[0] == _SHT_DYNAMIC]
    if not dyn:
        raise ValueError(f"{path}: no dynamic section (not a shared library?)")
    _, offset, size, link = dyn[0]
    strtab_off = sections[link][1]
    fmt, step = (end + "qQ", 16) if is64 else (end + "iI", 8)
    names = []
    for pos in range(offset, offset + size, step):
        tag, val = struct.unpack_from(fmt, data, pos)
        if tag == _DT_NULL:
            break
        if tag == _DT_NEEDED:
            stop = data.index(b"\0", strtab_off + val)
            names.append(data[strtab_off + val:stop].decode("utf-8", "replace"))
    return names


def links_libstdcxx_statically(path: os.PathLike | str) -> bool:
    """Whether a C++ library carries its own libstdc++ (it does not need ``libstdc++.so.6``)."""
    return not any(n.startswith("libstdc++.so") for n in needed_libraries(path))


@dataclass(frozen=True)
class Compiler:
    """A C++ compiler as named, where it resolves to, and its ``--version`` line."""

    name: str
    path: str
    version: str

    def __str__(self) -> str:
        return f"{self.name} ({self.path}: {self.version})" if self.path != self.name else \
            f"{self.name} ({self.version})"


#: How long a compiler's ``--version`` may take (every process asks it, for the build key):
#: a compiler wrapper that hangs costs each process this long, not a minute.
VERSION_TIMEOUT_S = 10.0


def compiler_identity(name: Optional[str] = None) -> Compiler:
    """The compiler ``name`` (default ``$CXX``, else ``c++``, as torch's build uses): its
    resolved path and the first line of ``--version`` ("" path where it is not found)."""
    name = name or os.environ.get("CXX") or "c++"
    found = shutil.which(name)
    if found is None:
        return Compiler(name, "", "not found")
    try:
        out = subprocess.run([found, "--version"], capture_output=True, text=True, timeout=VERSION_TIMEOUT_S).stdout
        version = (out.strip().splitlines() or ["no --version output"])[0].strip()
    except subprocess.TimeoutExpired:
        version = f"--version did not answer within {VERSION_TIMEOUT_S:g} s"
    except (OSError, subprocess.SubprocessError) as exc:
        version = f"--version failed: {exc}"
    return Compiler(name, os.path.realpath(found), version)


def dynamic_compiler(static: Compiler) -> Optional[Compiler]:
    """A compiler to build with instead of ``static`` (which linked libstdc++ statically):
    ``$COBGS_CXX`` when set, else ``c++`` / ``g++`` on the PATH, skipping ``static`` itself."""
    chosen = os.environ.get("COBGS_CXX")
    names = [chosen] if chosen else ["c++", "g++"]
    for n in names:
        c = compiler_identity(n)
        if c.path and (chosen or c.path != static.path):
            return c
    return None


def static_message(cxx: Compiler, found: str) -> str:
    """The build failure for a compiler that links libstdc++ statically, with the fix."""
    return (f"$CXX = {cxx.name} ({cxx.path or 'not found'}; {cxx.version}) links libstdc++ statically into the "
            f"native extension: {found}. Such a library crashes, or loses the numbers of its messages, on its "
            f"first C++ error (it runs its own copy of libstdc++ beside torch's). No other compiler was found "
            f"to build with (COBGS_CXX, c++ or g++ on the PATH). Fix: build with a compiler that links "
            f"libstdc++ dynamically, e.g. `CXX=g++ cobgs build` (or set COBGS_CXX to one)")


@dataclass(frozen=True)
class ProbeResult:
    """What the error probe saw: ``ok``, and otherwise what went wrong, in words."""

    ok: bool
    detail: str
    message: str = ""  # the RuntimeError's first line, as Python received it

    def to_json(self) -> dict:
        return asdict(self)


_PROBE_CHILD = """
import json, sys
import torch
lib, ns, arg = sys.argv[1], sys.argv[2], int(sys.argv[3])
torch.ops.load_library(lib)
op = getattr(getattr(torch.ops, ns), "error_probe")
try:
    op(arg)
except RuntimeError as exc:
    print(json.dumps({"raised": str(exc).splitlines()[0] if str(exc) else ""}))
else:
    print(json.dumps({"raised": None}))
"""


def probe_library(path: os.PathLike | str, namespace: str = "cobgs", timeout: float = 300.0) -> ProbeResult:
    """Load the library at ``path`` in a child process and call ``<namespace>::error_probe``
    with bad input: it must raise a ``RuntimeError`` whose message is :data:`PROBE_MESSAGE`."""
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE_CHILD, os.fspath(path), namespace, str(PROBE_ARG)],
                              capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return ProbeResult(False, f"the probe did not return within {timeout:g} s")
    if proc.returncode < 0:
        name = signal.Signals(-proc.returncode).name
        return ProbeResult(False, f"the process died of {name} in the library's error path instead of raising "
                                  "a RuntimeError")
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return ProbeResult(False, f"the probe could not run (exit code {proc.returncode}): {tail}")
    try:
        raised = json.loads(proc.stdout.strip().splitlines()[-1])["raised"]
    except (ValueError, IndexError, KeyError, TypeError):
        return ProbeResult(False, f"the probe printed nothing readable: {proc.stdout[-200:]!r}")
    if raised is None:
        return ProbeResult(False, "the error probe raised no error")
    if PROBE_MESSAGE not in raised:
        return ProbeResult(False, f"the library's error message lost its numbers: Python received {raised!r}, "
                                  f"the library wrote {PROBE_MESSAGE!r}", raised)
    return ProbeResult(True, "a C++ error reaches Python as a RuntimeError with its numbers", raised)
