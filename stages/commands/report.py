"""``cobgs report WORKFLOW [--out DIR] [--cache-dir D] [--set K=V]...``: the HTML report.

Builds one self-contained folder (``index.html`` + assets, relative links, no network)
from the workflow's cache entries alone, so any finished run, or a partly failed one, can
be re-reported at any time. The builder lives in ``reports/`` and is imported only when
the command runs (``cobgs --help`` stays fast).
"""

from __future__ import annotations


def register(sub) -> None:
    from . import frame_count

    p = sub.add_parser("report", help="build the HTML report of a workflow from its cache",
                       description="Build the HTML result report of a workflow from the cache "
                       "manifests and artifacts (nothing is recomputed). Default folder: "
                       "runs/reports/<workflow name>.")
    p.add_argument("workflow", help="workflow TOML file")
    p.add_argument("--out", help="report folder (default runs/reports/<workflow name>). It must be absent, "
                                 "empty or an earlier report of cobgs: that report is replaced as a whole. "
                                 "Any other folder is refused, and so is an earlier report that holds files "
                                 "cobgs did not write, unless --replace is given")
    p.add_argument("--replace", action="store_true",
                   help="replace an earlier report of cobgs even where files were added to it (they are deleted)")
    from pipeline.commands import add_cache_dir, add_sets

    add_sets(p)
    add_cache_dir(p)
    p.add_argument("--turntables", type=frame_count, default=0, metavar="N",
                   help="per method and object, N-frame orbit GIFs of the object alone and of the scene "
                        "without it (rendered on the CPU while building; 0 = none)")
    p.add_argument("--no-viewer", action="store_true",
                   help="leave out the interactive 3D viewers (and their embedded Gaussians): a small report")
    p.add_argument("--viewer-mb", type=_megabytes, default=None, metavar="MB",
                   help="cap of the embedded Gaussians per scene, in MB (default 8); a scene over it is "
                        "subsampled, most opaque x largest Gaussians first, and the page says so")
    p.add_argument("--trajectories", metavar="DIR", default=None,
                   help="a folder of tests/benchmarks/bm_refine_trajectory.py records: the refinement "
                        "section draws IoU / boundary IoU after every stage, per scene of this run")
    p.set_defaults(func=_report)


def _megabytes(text: str) -> float:
    import argparse
    import math

    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected a size in MB > 0, got {text!r}")
    return v


def build_report(workflow_path, **kw):
    """:func:`reports.build_report` with the program's stage registry and the stages' scene
    reader (for turntables and 3D viewers): the command layer hands ``reports/`` what it needs,
    so that ``reports/`` imports nothing of ``stages/``. Keywords as there."""
    from reports.builder import build_report as build
    from stages._common import scene_cameras
    from stages.registry import load_registry

    kw.setdefault("registry", load_registry())
    kw.setdefault("scene_cameras", scene_cameras)
    return build(workflow_path, **kw)


def _report(args) -> int:
    import sys

    from pipeline import PipelineError
    from reports.errors import ReportError

    try:
        index = build_report(args.workflow, out_dir=args.out, cache_dir=args.cache_dir, sets=args.sets,
                             stream=sys.stdout, turntables=args.turntables,
                             viewer=not args.no_viewer, viewer_mb=args.viewer_mb,
                             trajectories=args.trajectories, replace=args.replace)
    except (PipelineError, ReportError) as exc:  # bad workflow, --set or --out: the message names it
        print(f"cobgs report: error: {exc}", file=sys.stderr)
        return 2
    print(f"open file://{index.resolve()}")
    return 0
