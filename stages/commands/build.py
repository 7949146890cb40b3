"""``cobgs build``: compile the native rasterizer ahead of time."""

from __future__ import annotations


def _run(args) -> int:
    from cobgs.render import build

    path = build.load_extension(verbose=args.verbose, force=args.force)
    print(f"cobgs native extension ready: {path}")
    plan = build.cuda_plan()
    if plan["enabled"]:
        print(f"CUDA kernels: built for compute capability {plan['arch']} "
              f"(nvcc {plan['nvcc_version']}, {plan['nvcc']})")
    else:
        print(f"CUDA kernels: not built ({plan['reason']}); the CPU kernels serve "
              f"device=cpu")
    return 0


def register(sub) -> None:
    p = sub.add_parser("build", help="compile the native rasterizer now (otherwise on first use); "
                       "CUDA kernels too where torch has CUDA and a matching nvcc exists "
                       "(TORCH_CUDA_ARCH_LIST, MAX_JOBS, COBGS_CUDA=0/1: see cobgs/render/build.py)")
    p.add_argument("--force", action="store_true", help="rebuild even if a build is cached")
    p.add_argument("-v", "--verbose", action="store_true", help="show the compiler output")
    p.set_defaults(func=_run)
