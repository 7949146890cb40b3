"""The ``cobgs`` command line.

Commands are contributed by provider modules, each exposing ``register(subparsers)``
that adds its sub-commands with ``set_defaults(func=callable(args) -> int)``. Providers
must keep their module-level imports light (torch and friends are imported inside the
command functions) so that ``cobgs --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional, Sequence

# Order here is the order of `cobgs --help`.
PROVIDERS = (
    "stages.commands.build",
    "stages.commands.doctor",
    "stages.commands.new",
    "stages.commands.synth",
    "stages.commands.workflow",
    "stages.commands.export",
    "stages.commands.onnx",
    "stages.commands.report",
)


def build_parser() -> argparse.ArgumentParser:
    from cobgs import __version__

    parser = argparse.ArgumentParser(
        prog="cobgs",
        description="COB-GS segmentation of 3D Gaussian Splatting scenes, and the "
        "cached benchmark pipeline around it.",
    )
    parser.add_argument("--version", action="version", version=f"cobgs {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in PROVIDERS:
        importlib.import_module(name).register(sub)
    return parser


#: The top-level packages of this distribution besides cobgs (docs/install_names.md).
SIBLINGS = ("pipeline", "stages", "reports")


def check_sibling_packages() -> Optional[str]:
    """Why the top-level packages this program imports are not the ones installed beside
    ``cobgs`` (another distribution's ``pipeline`` or ``reports`` first on sys.path), or None."""
    import importlib.util
    from pathlib import Path

    home = Path(importlib.util.find_spec("cobgs").origin).resolve().parents[1]
    for name in SIBLINGS:
        spec = importlib.util.find_spec(name)
        where = Path(spec.origin).resolve().parents[1] if spec is not None and spec.origin else None
        if where != home:
            found = spec.origin if spec is not None and spec.origin else "nowhere"
            return (f"the package {name!r} imported here is {found}, not the one installed with cobgs (in {home}): "
                    f"another distribution provides a top-level {name!r}. Install cobgs in its own virtual "
                    "environment (docs/install_names.md)")
    return None


def main(argv: Optional[Sequence[str]] = None) -> int:
    # OpenMP threads that spin while waiting burn the cores they wait for: on a shared or
    # oversubscribed host, torch's 2-thread ops then run ~10x slower than 1 thread (measured:
    # 1.39 vs 0.056 s per training iteration on the demo scene at load 11 on 2 cores).
    # Passive waiting must be chosen before the OpenMP runtime loads (before torch is
    # imported); an explicit setting in the environment wins.
    import os

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    clash = check_sibling_packages()
    if clash:
        print(f"cobgs: error: {clash}", file=sys.stderr)
        return 2
    # Large per-iteration tensors reuse freed memory instead of page-faulting fresh
    # mmaps (cobgs/memory.py: about 10 % of a training iteration).
    from cobgs.memory import retain_freed_memory

    retain_freed_memory()
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    from cobgs.errors import CobgsError

    try:
        return int(func(args) or 0)
    except CobgsError as exc:  # expected failures: one clear line, no traceback
        print(f"cobgs {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `cobgs run --dry-run | head`: the reader left, nothing to say
        # Python flushes stdout again at exit; point it at /dev/null so that flush is silent.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a command killed by it


if __name__ == "__main__":
    sys.exit(main())
