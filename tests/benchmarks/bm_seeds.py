"""The baselines' own variance (issue 59 item 1): make bench's comparisons on several trained
baselines of the same scene, SfM seeds x training seeds, with intervals that hold that spread.

Two steps (not collected by pytest)::

    # 1. a workflow: the coarse scenes of synthetic_bench.toml, each again with other SfM and
    #    training seeds (`shares` the scene: same dataset and masks; the SfM reruns where its
    #    seed differs, the training where either does), the rows compared, every object
    .venv/bin/python tests/benchmarks/bm_seeds.py write runs/seed_spread.toml
    #    (or a smaller design: --pairs 0:0,1:0,2:0,0:1 --rows raem_paper,flashsplat, as
    #    docs/benchmarks/segmentation.md ran it)
    cobgs run runs/seed_spread.toml --cache-dir runs/cache -j 2
    # 2. the table: per scene, mask route and protocol, the default minus each row on every
    #    baseline, and pooled over the baselines with a two-level bootstrap
    .venv/bin/python tests/benchmarks/bm_seeds.py table runs/seed_spread.toml --cache runs/cache

The seed-0 scenes are synthetic_bench's own (same params, same cache keys): a cache that ran
`make bench` already holds them. Verdicts: **holds** (every baseline's own interval on the same
side of zero), **pooled only** (the pooled interval excludes zero, some baseline's does not),
**depends on the seed** (baselines significant on both sides), **no difference** (the pooled
interval holds zero).
"""

from __future__ import annotations

import argparse
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

SCENES = ("forward_coarse", "orbit_coarse")
SFM_SEEDS = (0, 1, 2)
TRAIN_SEEDS = (0, 1)
#: the default, then the rows issue 59 compares it with: its predecessor (no object-share split),
#: its faithful twin, NG-GS under the default and as released, and the best peer of the
#: occlusion-aware rows (FlashSplat, bias 0)
REF = "ours_per_use"
ROWS = ("ours_per_use_eq6", "raem_paper", "ngs_checked", "ngs", "flashsplat")
PROTOCOLS = {"biou": "headline mBIoU", "biou_occlusion": "occlusion-aware mBIoU"}
ROUTES = ("dataset masks", "dataset masks + noise")


def variant_name(scene: str, s: int, t: int) -> str:
    return scene if (s, t) == (0, 0) else f"{scene}_s{s}t{t}"


def _inline(value) -> str:
    """A TOML value (scalars, lists, inline tables) as text."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_inline(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_inline(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"cannot write {value!r} as TOML")


def _blocks(text: str, prefix: str) -> dict:
    """``[prefix.NAME]`` section texts of ``text``, by NAME (up to the next section or comment rule)."""
    out = {}
    pat = re.compile(r"^\[" + re.escape(prefix) + r"\.(\"[^\"]+\"|[\w.-]+)\][^\n]*\n(?:(?!\[|# ---).*\n)*", re.M)
    for m in pat.finditer(text):
        out[m.group(1).strip('"')] = m.group(0)
    return out


def write_workflow(src: Path, out: Path, scenes=SCENES, sfm_seeds=SFM_SEEDS, train_seeds=TRAIN_SEEDS,
                   rows=(REF, *ROWS), pairs=None) -> Path:
    """The seed-spread workflow from ``src`` (synthetic_bench.toml): its header and params as they
    are, the ``rows`` (methods) as they are, and each scene in ``scenes`` once per (SfM seed,
    training seed) with its objects: every pair of ``sfm_seeds`` x ``train_seeds``, or the
    ``pairs`` given (a smaller design, e.g. each SfM seed with training seed 0 and one more
    training seed on SfM seed 0)."""
    pairs = [(s, t) for s in sfm_seeds for t in train_seeds] if pairs is None else list(pairs)
    if (0, 0) not in pairs:
        raise SystemExit("the pairs must hold (0, 0): synthetic_bench's own scene")
    text = src.read_text(encoding="utf-8")
    doc = tomllib.loads(text)
    head = text[: text.index("# --- scenes")]
    head = head.replace(f'name = "{doc["workflow"]["name"]}"', 'name = "seed_spread"', 1)
    methods = _blocks(text, "axes.method")
    missing = [r for r in rows if r not in methods]
    if missing:
        raise SystemExit(f"{src}: no method {missing} to compare")
    parts = [head, "# --- scenes: each coarse scene on several SfM and training seeds (bm_seeds.py) ---\n"]
    objects = []
    for scene in scenes:
        table = dict(doc["axes"]["scene"][scene])
        objs = [(name, attrs) for name, attrs in doc["axes"]["object"][scene].items()]
        for s, t in pairs:
            name = variant_name(scene, s, t)
            tab = {k: (dict(v) if isinstance(v, dict) else v) for k, v in table.items()}
            if (s, t) != (0, 0):
                tab = {"shares": scene, **tab}
            if s:
                sfm = dict(tab.get("sfm", {}))
                sfm["options"] = {**dict(sfm.get("options", {})), "seed": s}
                tab["sfm"] = sfm
            if t:
                tab["train"] = {**dict(tab.get("train", {})), "seed": t}
            parts.append(f"[axes.scene.{name}]\n" + "".join(f"{k} = {_inline(v)}\n" for k, v in tab.items()) + "\n")
            for oname, attrs in objs:
                objects.append(f"[axes.object.{name}.{oname}]\n"
                               + "".join(f"{k} = {_inline(v)}\n" for k, v in attrs.items()))
    parts.append("# --- methods: the default and the rows it is compared with ---\n")
    parts += [methods[r] + ("" if methods[r].endswith("\n\n") else "\n") for r in rows]
    parts.append("# --- objects: each scene's, on every seed ---\n")
    parts += objects
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("".join(parts), encoding="utf-8")
    return out


def spread_table(workflow: Path, cache: Path, scenes=SCENES, rows=None, ref: str = REF) -> str:
    """The Markdown table of the module docstring; ``ref`` is the row the others are compared
    with (the default, unless a candidate is measured against everything)."""
    from bm_rows import METRICS, load

    from cobgs.evaluate.protocols import bootstrap_across_baselines, bootstrap_mean_diff

    name = "default" if ref == REF else ref
    out = [f"| scene | masks | protocol | {name} − row | per baseline (s,t) | pooled [95 %] | verdict |",
           "|---|---|---|---|---|---|---|"]
    axes = tomllib.loads(workflow.read_text(encoding="utf-8"))["axes"]
    present, methods = set(axes["scene"]), list(axes["method"])
    rows = [r for r in (methods if rows is None else rows) if r in methods and r != ref]  # the workflow's rows
    for route in ROUTES:
        R, _ = load(workflow, cache, (), route)
        for scene in scenes:
            bases = [(s, t, variant_name(scene, s, t)) for s in SFM_SEEDS for t in TRAIN_SEEDS
                     if variant_name(scene, s, t) in present]
            for metric, label in PROTOCOLS.items():
                for row in rows:
                    pairs, singles = {}, {}
                    for s, t, b in bases:
                        objs = sorted({o for (sc, m, o) in R if (sc, m) == (b, ref)}
                                      & {o for (sc, m, o) in R if (sc, m) == (b, row)})
                        p = {}
                        for o in objs:
                            pa = R[(b, ref, o)]["details"][METRICS[metric]]
                            pb = R[(b, row, o)]["details"][METRICS[metric]]
                            p[o] = [(pa[v]["biou"], pb[v]["biou"]) for v in pa if v in pb]
                        if p:
                            pairs[f"s{s}t{t}"] = p
                            singles[f"s{s}t{t}"] = bootstrap_mean_diff(p)
                    pooled = bootstrap_across_baselines(pairs)
                    if pooled is None:
                        continue
                    sig = {k: (d["lo"] > 0) - (d["hi"] < 0) for k, d in singles.items() if d}
                    if pooled["lo"] <= 0 <= pooled["hi"]:
                        verdict = "no difference"
                    elif 1 in sig.values() and -1 in sig.values():
                        verdict = "depends on the seed"
                    elif all(v == (1 if pooled["diff"] > 0 else -1) for v in sig.values()):
                        verdict = "holds"
                    else:
                        verdict = "pooled only"
                    per = ", ".join(f"{k[1]},{k[3]}: {d['diff']:+.2f}" for k, d in singles.items() if d)
                    out.append(f"| {scene} | {route} | {label} | {ref} − {row} | {per} | {pooled['diff']:+.2f} "
                               f"[{pooled['lo']:+.2f}, {pooled['hi']:+.2f}] ({pooled['baselines']}) | {verdict} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write", help="write the seed-spread workflow")
    w.add_argument("out", type=Path)
    w.add_argument("--source", type=Path, default=ROOT / "workflows" / "synthetic_bench.toml")
    w.add_argument("--pairs", help="SfM:training seed pairs, comma separated (default: every pair of "
                   f"{SFM_SEEDS} x {TRAIN_SEEDS}), e.g. 0:0,1:0,2:0,0:1")
    w.add_argument("--rows", help=f"the rows compared with {REF}, comma separated (default: {','.join(ROWS)})")
    t = sub.add_parser("table", help="the comparisons on every baseline and pooled")
    t.add_argument("workflow", type=Path)
    t.add_argument("--cache", type=Path, required=True)
    t.add_argument("--ref", default=REF, help=f"the row every other is compared with (default {REF})")
    args = ap.parse_args(argv)
    if args.cmd == "write":
        pairs = None
        if args.pairs:
            try:
                pairs = [tuple(int(x) for x in p.split(":")) for p in args.pairs.split(",")]
            except ValueError:
                raise SystemExit(f"--pairs {args.pairs!r}: expected S:T pairs of integers, comma separated")
            if any(len(p) != 2 or p[0] not in SFM_SEEDS or p[1] not in TRAIN_SEEDS for p in pairs):
                raise SystemExit(f"--pairs {args.pairs!r}: each S:T with S in {SFM_SEEDS} and T in {TRAIN_SEEDS}")
        rows = (REF, *(args.rows.split(",") if args.rows else ROWS))
        print(write_workflow(args.source, args.out, pairs=pairs, rows=rows))
    else:
        print(spread_table(args.workflow, args.cache, ref=args.ref))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
