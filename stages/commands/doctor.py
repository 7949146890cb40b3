"""``cobgs doctor``: what this machine builds and runs, checked (a bug report's first lines).

It prints the compiler, torch, CUDA and nvcc versions, the native extension's path and how it
was built, then checks: the extension's error probe (a C++ error must reach Python as a
``RuntimeError`` holding its numbers, :mod:`cobgs.render.toolchain`), a small render on every
device against the pure-PyTorch reference (:func:`cobgs.render.selfcheck.parity`), and the
forward + backward time of one 100k-Gaussian render per device. Exit code 1 when any check
fails; ``--json FILE`` (``-``: standard output) writes the same as one JSON record.
"""

from __future__ import annotations

import json
import os
import platform
import sys


def collect(timing: bool = True) -> dict:
    """Everything ``cobgs doctor`` reports, as a JSON-able record with ``ok``."""
    import torch

    from cobgs import __version__
    from cobgs.errors import BuildError
    from cobgs.render import build
    from cobgs.render.toolchain import compiler_identity, probe_library
    from cobgs.render.selfcheck import parity, timing as time_render

    rec: dict = {"cobgs": __version__, "python": platform.python_version(),
                 "platform": f"{platform.system()} {platform.machine()}", "cpus": os.cpu_count(),
                 "torch": torch.__version__, "torch_cuda": torch.version.cuda,
                 "threads": torch.get_num_threads(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}
    cxx = compiler_identity()
    rec["compiler"] = {"CXX": os.environ.get("CXX"), "name": cxx.name, "path": cxx.path, "version": cxx.version}
    if os.environ.get("COBGS_CXX"):
        alt = compiler_identity(os.environ["COBGS_CXX"])
        rec["compiler"]["COBGS_CXX"] = {"path": alt.path, "version": alt.version}
    devices = ["cpu"]
    try:
        if torch.cuda.is_available():
            devices += [f"cuda:{i}" for i in range(torch.cuda.device_count())]
            rec["gpus"] = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
    except Exception as exc:  # noqa: BLE001 - a broken driver is a finding, not a crash
        rec["gpus_error"] = f"{type(exc).__name__}: {exc}"
    try:
        plan = build.cuda_plan()
    except BuildError as exc:  # COBGS_CUDA=1 with a piece missing: the build below says it too
        plan = {"enabled": False, "reason": str(exc)}
    rec["cuda_plan"] = plan
    home = build.cuda_home()
    rec["nvcc"] = {"path": str(home / "bin" / "nvcc"), "version": build.nvcc_version(str(home / "bin" / "nvcc"))} \
        if home else None
    checks: dict = {}
    try:
        so = build.load_extension()
    except (BuildError, OSError) as exc:  # (an unwritable cache is a finding too: the record is printed)
        text = str(exc) if isinstance(exc, BuildError) else f"{type(exc).__name__}: {exc}"
        rec["extension"] = {"error": text[:4000]}
        checks["extension"] = {"ok": False, "detail": text.splitlines()[0]}
        rec["checks"], rec["ok"] = checks, False
        return rec
    from pathlib import Path

    from cobgs.render.toolchain import links_libstdcxx_statically

    built = build.read_probe(Path(so).parent) or {}
    # what the library's dynamic section says now, not what probe.json claims
    static = links_libstdcxx_statically(Path(so))
    rec["extension"] = {"path": so, "build_key": build.build_key()[:16], "cflags": build.cflags(),
                        "ldflags": build.LDFLAGS, "cuda_flags": build.CUDA_FLAGS if plan.get("enabled") else None,
                        "built_with": built.get("compiler"), "switched_from": built.get("switched_from"),
                        "libstdcxx": "static" if static else "dynamic",
                        "cuda_kernels": bool(plan.get("enabled"))}
    checks["libstdcxx"] = {"ok": not static, "detail": "the library links libstdc++ statically: its C++ errors "
                           "would not reach Python intact (rebuild: `cobgs build --force`)" if static else
                           "linked dynamically"}
    from cobgs.render.ops import cuda_fast_path_on

    rec["extension"]["cuda_blend_path"] = "fast" if cuda_fast_path_on() else "exact"
    probe = probe_library(so)
    checks["error_probe"] = {"ok": probe.ok, "detail": probe.detail, "message": probe.message}
    for dev in devices:
        p = parity(dev)
        checks[f"render_{dev}"] = {"ok": p.ok, **p.to_json()}
        if timing:
            t = time_render(dev)
            rec.setdefault("timing", {})[dev] = t.to_json()
            if t.error:
                checks[f"timing_{dev}"] = {"ok": False, "detail": t.error}
    rec["checks"] = checks
    rec["ok"] = all(c.get("ok") for c in checks.values())
    return rec


def _text(rec: dict) -> str:
    from cobgs.render.selfcheck import GRAD_RTOL_OF_MAX, IMAGE_ATOL

    c = rec["compiler"]
    lines = [f"cobgs doctor: cobgs {rec['cobgs']}, Python {rec['python']}, {rec['platform']}, {rec['cpus']} CPUs",
             f"torch       {rec['torch']} (CUDA {rec['torch_cuda'] or 'none'}; {rec['threads']} threads, "
             f"OMP_WAIT_POLICY={rec['omp_wait_policy'] or 'unset'})",
             f"GPUs        {', '.join(rec['gpus']) if rec.get('gpus') else rec.get('gpus_error', 'none visible')}",
             f"compiler    {c['name']} -> {c['path'] or 'not found'}: {c['version']}"
             + ("" if c["CXX"] else "   ($CXX unset)"),
             f"nvcc        {rec['nvcc']['version']} ({rec['nvcc']['path']})" if rec.get("nvcc") else "nvcc        not found"]
    if "COBGS_CXX" in c:
        lines.append(f"COBGS_CXX   {c['COBGS_CXX']['path']}: {c['COBGS_CXX']['version']}")
    ext = rec["extension"]
    if "error" in ext:
        lines.append(f"extension   FAILED to build: {ext['error'].splitlines()[0]}")
    else:
        plan = rec["cuda_plan"]
        lines += [f"extension   {ext['path']}",
                  f"            built with {ext['built_with'] or 'a compiler not recorded (before the checks)'}"
                  + (f" (instead of {ext['switched_from']}, which links libstdc++ statically)" if ext["switched_from"]
                     else "") + f"; libstdc++: {ext['libstdcxx'] or 'unknown'}",
                  f"            flags {' '.join(ext['cflags'])}; link {' '.join(ext['ldflags'])}",
                  "            CUDA kernels: " + (f"built for {plan['arch']} (nvcc {plan['nvcc_version']})"
                                                  if plan.get("enabled") else f"not built ({plan.get('reason')})")
                  + (f"; blending path: {ext['cuda_blend_path']} (COBGS_CUDA_EXACT=1: exact)"
                     if plan.get("enabled") and ext.get("cuda_blend_path") else "")]
    checks = rec["checks"]
    if "error_probe" in checks:
        ep = checks["error_probe"]
        lines.append(f"error probe {'ok' if ep['ok'] else 'FAILED'}: {ep['detail']}")
    for name, chk in checks.items():
        if not name.startswith("render_"):
            continue
        dev = name[len("render_"):]
        if chk.get("error"):
            lines.append(f"render {dev:<5}FAILED: {chk['error']}")
            continue
        worst = max(chk["grad_max_rel"].values()) if chk["grad_max_rel"] else float("nan")
        lines.append(f"render {dev:<5}{'ok' if chk['ok'] else 'FAILED'}: float32 native vs float64 reference: "
                     f"image {chk['image_max_abs']:.1e} (<= {IMAGE_ATOL:g}), alpha {chk['alpha_max_abs']:.1e}, "
                     f"gradients {worst:.1e} of their largest (<= {GRAD_RTOL_OF_MAX:g}), radii "
                     f"{'equal' if chk['radii_equal'] else 'DIFFER'}")
    for dev, t in (rec.get("timing") or {}).items():
        if t["error"]:
            lines.append(f"timing {dev:<5}FAILED: {t['error']}")
        else:
            lines.append(f"timing {dev:<5}{t['n']} Gaussians at {t['width']}x{t['height']}, forward + backward: "
                         f"{t['fwd_bwd_ms']:.1f} ms median of {t['reps']} (min {t['fwd_bwd_ms_min']:.1f})"
                         + (f", {t['threads']} threads" if t["threads"] else ""))
    failed = [k for k, v in checks.items() if not v.get("ok")]
    lines.append("result      all checks passed" if not failed else f"result      FAILED: {', '.join(failed)}")
    return "\n".join(lines)


def _doctor(args) -> int:
    if args.json and args.json != "-":  # before minutes of checks: where the record goes must exist
        folder = os.path.dirname(os.path.abspath(args.json))
        if not os.path.isdir(folder) or os.path.isdir(args.json):
            print(f"cobgs doctor: --json {args.json}: " + (f"the folder {folder} does not exist" if not os.path.isdir(
                folder) else "is a folder; give the file to write"), file=sys.stderr)
            return 2
    rec = collect(timing=not args.no_timing)
    if args.json == "-":
        print(json.dumps(rec, indent=1, default=str))
    else:
        print(_text(rec))
        if args.json:
            try:
                with open(args.json, "w", encoding="utf-8") as f:
                    json.dump(rec, f, indent=1, default=str)
            except OSError as exc:
                print(f"cobgs doctor: cannot write --json {args.json}: {exc.strerror}", file=sys.stderr)
                return 2
            print(f"record: {args.json}")
    return 0 if rec["ok"] else 1


def register(sub) -> None:
    p = sub.add_parser("doctor", help="check this machine: compiler, torch, CUDA, the extension's error path, "
                       "a render against the reference per device, and its speed",
                       description="Print the compiler, torch, CUDA and nvcc versions and how the native "
                       "extension was built; check that a C++ error reaches Python intact, that a small render "
                       "matches the pure-PyTorch reference on every device, and time a 100k-Gaussian render. "
                       "Exit code 1 when a check fails. Paste its output into a bug report.")
    p.add_argument("--json", metavar="FILE", help="also write the record as JSON to FILE ('-': print only the JSON)")
    p.add_argument("--no-timing", action="store_true", help="skip the 100k-Gaussian timing")
    p.set_defaults(func=_doctor)
