"""Where a row's in-scene mask gets its pixels: its own evaluation render beside the raw render
of its labels at two bars (issue 59: LUDVIG's occlusion-aware lead on forward_coarse).

For each done refine entry of ``--row`` on ``--scene``, the labels (``mask_values``) of every
Gaussian are rendered in the scene at each held-out view and scored against the view's visible
mask (the occlusion-aware protocol's GT) three ways: the row's own render
(:func:`cobgs.refine.segment.visible_object_mask` of its in-scene set, the segment stage's
``pred_visible``; for LUDVIG the min-max normalised render above its bar), the raw render above
the row's bar, and the raw render above 0.5. Prints pooled precision and recall and the mean BIoU over the views.

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_render_bar.py workflows/synthetic_bench.toml --cache CACHE \\
        --scene forward_coarse --row ludvig --objects ball,ball_noisy,pole
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workflow", type=Path)
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--row", required=True)
    ap.add_argument("--objects", default="", help="comma list (default: every object of the row)")
    a = ap.parse_args(argv)

    import numpy as np
    import torch

    from cobgs.evaluate.protocols import compare_masks
    from cobgs.refine.segment import method_threshold, visible_object_mask
    from cobgs.render.image import render
    from pipeline import entries, load_workflow
    from stages._common import Files, load_scene, read_json
    from stages.registry import load_registry
    from stages.segment import read_refined

    wanted = {o for o in a.objects.split(",") if o}
    wf = load_workflow(a.workflow, load_registry(), [])
    refined, dataset, poses = {}, None, None
    for rec in entries(wf, a.cache):
        v = rec.item.values
        if rec.state != "done" or v.get("scene") != a.scene:
            continue
        if rec.stage == "refine" and v.get("method") == a.row and (not wanted or v["object"] in wanted):
            refined[v["object"]] = Path(rec.output("refined"))
        elif rec.stage == "dataset":
            dataset = Path(rec.output("dataset"))
        elif rec.stage == "sfm":
            poses = Path(rec.output("poses"))
    if not refined or dataset is None or poses is None:
        raise SystemExit(f"no done refine entry of row {a.row!r} on scene {a.scene!r} in {a.cache}")
    scene = load_scene(dataset, poses)
    print(f"| {a.scene}, {a.row} | its own render | raw render > its bar | raw render > 0.5 |")
    print("|---|---|---|---|")
    for obj, d in sorted(refined.items()):
        ref = read_json(d / Files.REFINE)
        _, in_scene, _ = read_refined(d, "cpu")
        model, values = in_scene.model, in_scene.mask_values.float()
        bar = method_threshold(in_scene)
        gt_name = ref.get("dataset_object") or ref.get("object") or obj
        counts = {k: [0, 0, 0, []] for k in ("own", "bar", "half")}
        for v in scene.test:
            gt = v.masks.get(gt_name)
            if gt is None or not bool(gt.any()):
                continue
            gt = gt.cpu().numpy()
            with torch.no_grad():
                img = render(model, v.camera, None, features=values[:, None].to(model.means.dtype).contiguous()).image[..., 0]
            own = visible_object_mask(in_scene, v.camera)  # pred_visible, as the segment stage renders it
            for k, p in (("own", own), ("bar", img > bar), ("half", img > 0.5)):
                s = compare_masks(p.numpy(), gt)
                c = counts[k]
                c[0] += s.tp
                c[1] += s.fp
                c[2] += s.fn
                c[3].append(s.biou)

        def cell(c):
            return (f"{c[0] / max(1, c[0] + c[1]):.2f} / {c[0] / max(1, c[0] + c[2]):.2f} / "
                    f"{100 * float(np.mean(c[3])) if c[3] else float('nan'):.1f}")

        print(f"| {obj} (bar {bar:g}), precision / recall / mBIoU | {cell(counts['own'])} | {cell(counts['bar'])} | "
              f"{cell(counts['half'])} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
