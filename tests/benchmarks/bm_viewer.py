"""The report's WebGL2 splat viewer in headless Chromium on SwiftShader (no GPU): frames per
second, Gaussian counts, bytes, and agreement with cobgs.rasterize, on the demo report.

Run (not collected by pytest; needs Debian's chromium, `make chromium`)::

    make demo    # or: cobgs run workflows/demo.toml
    .venv/bin/python tests/benchmarks/bm_viewer.py [--report runs/reports/demo] [--frames 60] \\
        [--write docs/benchmarks/viewer.md]

Without ``--report`` it builds the demo report as `make demo` does (``--turntables 24``)
from ``--cache-dir`` (default runs/cache) into a temporary folder.

A frame: the camera orbits 6 px of drag, both sides' workers sort, both canvases draw, and
a 1-pixel read waits for the GPU work before the next frame starts (no overlap of sorting
and drawing, so this is a lower bound of what the page shows while dragging). "data
resolution": the canvas at the dataset cameras' own size (the viewer's default);
"screen": at the page's CSS size. Frame rates are absolute, so the load average is printed
beside them.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT / "tests" / "reports"))
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from report_browser import Browser  # noqa: E402
from test_viewer_browser import _camera, _png, _reference  # noqa: E402  (the tests' helpers)


def _folder_bytes(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def _packing_cost(report: Path, cfgs: list, cache_dir: str) -> list:
    """What the embedding itself costs, by cobgs.rasterize alone at training camera 0 (whole
    refined scene): the original PLYs with their SH bands vs degree 0 (the viewer's SH
    truncation), and vs the decoded 21-byte Gaussians (truncation + quantisation)."""
    from cobgs.render import splat_pack
    from cobgs.evaluate.metrics import psnr
    from cobgs.render.image import render_image
    from pipeline import load_workflow
    from reports.collect import collect
    from reports.viewer import _load, embedded
    from stages.registry import load_registry

    if not Path(cache_dir).is_dir():
        return ["", f"(packing cost not measured: no cache at {cache_dir})"]
    data = collect(load_workflow(ROOT / "workflows" / "demo.toml", load_registry()), Path(cache_dir))
    out = ["", "What the embedding costs (cobgs.rasterize alone, training camera 0, whole refined scene; "
           "PSNR in dB against the original Gaussians with all their SH bands):", "",
           "| viewer | method | Gaussians | degree 0 (SH truncation) | decoded 21-byte (truncation + quantisation) |",
           "|---|---|---|---|---|"]
    for cfg in cfgs:
        for method, rec in cfg["models"].items():
            scene, obj_name = rec["key"].split("/")[:2]
            r = next((r for r in data.results if (r.scene, r.object, r.method) == (scene, obj_name, method)), None)
            if r is None or r.segment_dir is None:
                continue
            merged = _load(Path(r.segment_dir))[0]  # what the report packs, with all its SH bands
            cam, bg = _camera(cfg, 0), cfg["background"]
            ref = render_image(merged, cam, bg).clamp(0, 1)
            deg0 = render_image(merged, cam, bg, sh_degree=0).clamp(0, 1)
            header, payload = embedded(report, rec)
            dec = render_image(splat_pack.unpacked_model(header, payload), cam, bg).clamp(0, 1)
            out.append(f"| {cfg['id']} | {method} | {header['count']:,} | {float(psnr(deg0, ref)):.2f} | "
                       f"{float(psnr(dec, ref)):.2f} |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--report", type=Path, help="a built demo report folder (default: build one)")
    ap.add_argument("--cache-dir", default="runs/cache")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--write", type=Path, help="write the results as Markdown here")
    args = ap.parse_args(argv)

    import numpy as np

    from reports.viewer import configs

    tmp = None
    report = args.report
    if report is None:
        from stages.commands.report import build_report

        tmp = tempfile.TemporaryDirectory(prefix="bm-viewer-")
        report = Path(tmp.name) / "demo"
        build_report(ROOT / "workflows" / "demo.toml", out_dir=report, cache_dir=args.cache_dir, turntables=24)
    report = report.resolve()
    cfgs = configs(report)
    if not cfgs:
        print(f"{report}: no viewer in this report", file=sys.stderr)
        return 2
    total, viewer = _folder_bytes(report), _folder_bytes(report / "viewer")
    lines = [f"Report {report}: {total / 1e6:.2f} MB in all, viewer data {viewer / 1e6:.2f} MB "
             f"({len(cfgs)} viewers, {cfgs[0]['bytes_per_gaussian']} bytes per Gaussian packed, "
             f"4/3 of that as base64 text)", ""]
    rows = []
    acc = []
    with Browser(width_px=1280, height_px=900, webgl=True, timeout_s=600) as b:
        b.goto((report / "index.html").as_uri())
        renderer = b.eval("(function(){var gl=document.createElement('canvas').getContext('webgl2');"
                          "var e=gl.getExtension('WEBGL_debug_renderer_info');"
                          "return e ? gl.getParameter(e.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);})()")
        for i, cfg in enumerate(cfgs):
            b.eval(f"document.querySelectorAll('details.viewer')[{i}].open = true")
            b.eval(f"window.cobgsStartViewer(document.querySelectorAll('details.viewer .viewer-box')[{i}])"
                   ".then(() => 1)")
            v = f"window.cobgsViewers[{i}]"
            obj = cfg["id"]
            for mode in ("object", "scene"):
                b.eval(f"{v}.setMode('{mode}')")
                for hires in (False, True):
                    b.eval(f"(function(){{var c={v}.box.querySelector('input.viewer-hires');"
                           f"if (c.checked !== {str(hires).lower()}) c.click();}})()")
                    b.eval(f"{v}.refresh().then(() => 1)")
                    size = b.eval(f"[{v}.sides[0].canvas.width, {v}.sides[0].canvas.height]")
                    counts = b.eval(f"{v}.sides.map(s => s.gpu.count)")
                    frames = args.frames if not hires else max(10, args.frames // 3)
                    fps = b.eval(f"{v}.measureFps({frames})")
                    load = os.getloadavg()[0]
                    rows.append((obj, mode, "screen" if hires else "data", f"{size[0]}x{size[1]}",
                                 " + ".join(f"{c:,}" for c in counts), f"{fps:.1f}", f"{load:.2f}"))
                    print(" | ".join(rows[-1]), flush=True)
                b.eval(f"(function(){{var c={v}.box.querySelector('input.viewer-hires'); if (c.checked) c.click();}})()")
                for side, method in enumerate((cfg["left"], cfg["right"])):
                    shot = _png(b.eval(f"{v}.snapshot(0, {side})"))
                    ref = _reference(report, cfg, method, mode, 0)
                    d = np.abs(shot.astype(np.int16) - ref.astype(np.int16))
                    acc.append((obj, mode, method, f"{d.mean():.3f}", f"{np.percentile(d, 99.9):.1f}", str(d.max())))
                    print(" | ".join(acc[-1]), flush=True)
                b.eval(f"{v}.setCamera(0)")
        errors = b.errors()
    lines += [f"Chromium renderer: {renderer}", "",
              "| viewer | mode | canvas | size | Gaussians drawn (left + right) | frames / s | load |",
              "|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    lines += ["", "Agreement with cobgs.rasterize at training camera 0 (same decoded Gaussians, 8-bit RGB):", "",
              "| viewer | mode | method | mean abs diff | p99.9 | max |", "|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(r) + " |" for r in acc]
    lines += ["", f"Console errors: {errors or 'none'}"]
    lines += _packing_cost(report, cfgs, args.cache_dir)
    text = "\n".join(lines)
    print(text)
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        head = ("# The report's splat viewer: speed, size, agreement with the rasterizer\n\n"
                "Written by `.venv/bin/python tests/benchmarks/bm_viewer.py --write docs/benchmarks/viewer.md` "
                "(headless Chromium, WebGL2 on SwiftShader, this 2-core machine, no GPU).\n\n")
        args.write.write_text(head + text + "\n", encoding="utf-8")
    if tmp is not None:
        tmp.cleanup()
    return 1 if errors else 0


if __name__ == "__main__":
    raise SystemExit(main())
