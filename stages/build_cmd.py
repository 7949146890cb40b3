"""``cobgs build``: compile the native rasterizer ahead of time."""

from __future__ import annotations


def _build(args) -> int:
    from cobgs import _build

    path = _build.load_extension(verbose=args.verbose, force=args.force)
    print(f"cobgs native extension ready: {path}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("build", help="compile the native rasterizer now (otherwise on first use)")
    p.add_argument("--force", action="store_true", help="rebuild even if a build is cached")
    p.add_argument("-v", "--verbose", action="store_true", help="show the compiler output")
    p.set_defaults(func=_build)
