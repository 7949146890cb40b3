"""Plots of the report, drawn with matplotlib (Agg) into SVG files.

Each function takes plain numbers that were measured by the run (nothing is fitted or
extrapolated) and writes one figure; the caller decides what to say when there is no data.
SVGs carry no date and use a fixed id salt, so rebuilding a report gives identical files.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

REFERENCE_COLOR = "#1b4f8a"
PALETTE = ("#d1495b", "#edae49", "#66a182", "#8d6cab", "#2e86ab", "#a0522d", "#6c757d", "#e07a5f")
STAGE_COLORS = {"dataset": "#bcbcbc", "sfm": "#9e9e9e", "train": "#6c757d", "masks": "#c9b37e",
                "heldout": "#dcdcdc", "refine": REFERENCE_COLOR, "segment": "#66a182", "evaluate": "#edae49",
                "summary": "#8d6cab"}


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    plt.rcParams.update({
        # Text stays text (smaller files, selectable, twice as fast to write); the page's
        # sans-serif fallbacks render it, no font file is needed.
        "svg.hashsalt": "cobgs-report", "svg.fonttype": "none", "font.size": 8.5,
        "font.family": ["DejaVu Sans", "sans-serif"],
        "axes.spines.top": False, "axes.spines.right": False, "axes.titlesize": 9,
        "axes.titleweight": "bold", "axes.labelsize": 8.5, "legend.fontsize": 8, "legend.frameon": False,
        "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.grid": True, "grid.color": "#e6e6e6",
        "grid.linewidth": 0.6, "axes.axisbelow": True, "figure.dpi": 100,
        # Labels are scene / method / object names, not TeX: "a$b" is drawn as typed (with
        # math text on, a lone "$" made matplotlib raise and the whole report fail).
        "text.parse_math": False,
    })
    return plt


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="svg", metadata={"Date": None})
    plt.close(fig)


def method_colors(methods: Sequence[str], reference: Optional[str]) -> dict[str, str]:
    """One colour per method, the same in every plot; the reference method in blue."""
    out, k = {}, 0
    for m in methods:
        if m == reference:
            out[m] = REFERENCE_COLOR
        else:
            out[m] = PALETTE[k % len(PALETTE)]
            k += 1
    return out


def iou_biou(path: Path, methods: Sequence[str], iou: Sequence[Optional[float]], biou: Sequence[Optional[float]],
             points: dict, colors: dict, labels: Optional[Sequence[str]] = None) -> bool:
    """Grouped bars of mIoU and mBIoU (%) per method; per-scene means as dots. ``labels``
    replace the method names on the axis (e.g. marked as incomplete)."""
    if not any(v is not None for v in list(iou) + list(biou)):
        return False
    plt = _plt()
    n = len(methods)
    fig, ax = plt.subplots(figsize=(max(4.0, 0.7 * n + 1.5), 2.8), layout="constrained")
    x = np.arange(n)
    w = 0.38
    for off, vals, name, hatch in ((-w / 2, iou, "mIoU", None), (w / 2, biou, "mBIoU", "///")):
        h = [100.0 * v if v is not None else 0.0 for v in vals]
        bars = ax.bar(x + off, h, w, color=[colors[m] for m in methods], edgecolor="white", hatch=hatch,
                      alpha=1.0 if hatch is None else 0.65, label=name)
        for b, v in zip(bars, vals):
            if v is not None:
                ax.annotate(f"{100 * v:.1f}", (b.get_x() + b.get_width() / 2, b.get_height()), ha="center",
                            va="bottom", fontsize=7, xytext=(0, 1), textcoords="offset points")
    for i, m in enumerate(methods):
        for a, b in points.get(m, []):
            if a is not None:
                ax.plot(i - w / 2, 100 * a, "o", ms=2.5, color="black", alpha=0.55, zorder=3)
            if b is not None:
                ax.plot(i + w / 2, 100 * b, "o", ms=2.5, color="black", alpha=0.55, zorder=3)
    ax.set_xticks(x, labels or methods, rotation=20 if n > 4 else 0, ha="right" if n > 4 else "center")
    ax.set_ylabel("%")
    # The axis spans the data, not 0-100: at benchmark scale the methods differ by 0.5-6
    # points, which a 0-100 axis flattens. The title says where the axis starts.
    vals = [100.0 * v for v in list(iou) + list(biou) if v is not None]
    vals += [100.0 * v for m in methods for pair in points.get(m, []) for v in pair if v is not None]
    lo, hi = min(vals), max(vals)
    pad = max(1.0, 0.1 * (hi - lo))
    bottom = max(0.0, float(np.floor(lo - pad)))
    ax.set_ylim(bottom, min(105.0, hi + 2 * pad) if hi + 2 * pad > bottom else 105.0)
    from matplotlib.patches import Patch

    ax.legend(handles=[Patch(facecolor="#888", label="mIoU"), Patch(facecolor="#888", alpha=0.65, hatch="///",
                                                                      edgecolor="white", label="mBIoU")],
              loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=2, borderaxespad=0.2, fontsize=8)
    # The legend sits on its own line above the axes, the title above it (a narrow figure
    # with few methods has no room for both side by side).
    ax.set_title("Segmentation accuracy per method" + (f" (axis from {bottom:.0f} %)" if bottom > 0 else ""),
                 loc="left", pad=22)
    _save(fig, path)
    return True


def psnr(path: Path, methods: Sequence[str], values: Sequence[Optional[float]], vanilla,
         colors: dict, labels: Optional[Sequence[str]] = None) -> bool:
    """Each method's held-out PSNR as a dot on a stem from the vanilla scene's PSNR: the stem
    is the change, and no bar pretends the axis starts at zero.

    ``vanilla``: one value for every method (a dashed line), or one per method (methods run
    on different scenes, e.g. a δ sweep limited to one scene): each stem then starts at its
    own method's vanilla mean, marked with a short tick, and the line is only drawn when all
    of them agree."""
    if not any(v is not None for v in values):
        return False
    plt = _plt()
    n = len(methods)
    fig, ax = plt.subplots(figsize=(5.0, 0.32 * n + 1.2), layout="constrained")
    y = np.arange(n)[::-1]
    vals = [v if v is not None else np.nan for v in values]
    per = list(vanilla) if isinstance(vanilla, (list, tuple)) else [vanilla] * n
    per = [v if v is not None and np.isfinite(v) else None for v in per]
    shared = {round(v, 6) for v in per if v is not None}
    common = per[0] if len(shared) == 1 and all(v is not None for v in per) else None
    for yi, v, m, van in zip(y, vals, methods, per):
        if not np.isfinite(v):
            continue
        if van is not None:
            ax.plot([van, v], [yi, yi], color=colors[m], lw=2.2, solid_capstyle="butt")
            if common is None:
                ax.plot([van], [yi], "|", color="black", ms=9, mew=1.2)
        ax.plot([v], [yi], "o", color=colors[m], ms=6)
        txt = f"{v:.2f}" + (f" ({v - van:+.2f})" if van is not None else "")
        right = van is None or v >= van
        ax.annotate(txt, (v, yi), xytext=(6 if right else -6, 0), textcoords="offset points", va="center",
                    ha="left" if right else "right", fontsize=7)
    finite = [v for v in vals if np.isfinite(v)] + [v for v in per if v is not None]
    lo, hi = min(finite), max(finite)
    pad = max(0.3, 0.35 * (hi - lo))
    ax.set_xlim(lo - pad, hi + pad)
    ax.set_ylim(-0.7, n - 0.3)
    if common is not None:
        ax.axvline(common, color="black", ls="--", lw=0.9)
        ax.annotate(f"vanilla {common:.2f}", (common, n - 0.45), xytext=(3, 0), textcoords="offset points",
                    fontsize=7, va="bottom")
    ax.set_yticks(y, labels or methods)
    ax.set_xlabel("PSNR on held-out views (dB)" + ("" if common is not None or not shared else
                  "\n| = the vanilla scenes' mean PSNR for that method's scenes"))
    ax.grid(axis="y", visible=False)
    ax.set_title("Texture quality per method (vs the vanilla scene)", loc="left")
    _save(fig, path)
    return True


def time_breakdown(path: Path, bars: Sequence[tuple[str, dict]], stages: Sequence[str]) -> bool:
    """Stacked horizontal bars of wall time (s) per stage; ``bars`` = [(label, {stage: s})]."""
    if not bars or not any(any(v for v in d.values()) for _, d in bars):
        return False
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 0.34 * len(bars) + 1.5), layout="constrained")
    y = np.arange(len(bars))[::-1]
    left = np.zeros(len(bars))
    for s in stages:
        vals = np.array([d.get(s, 0.0) or 0.0 for _, d in bars])
        if not vals.any():
            continue
        ax.barh(y, vals, 0.62, left=left, color=STAGE_COLORS.get(s, "#999"), label=s, edgecolor="white",
                linewidth=0.5)
        left += vals
    for yi, tot in zip(y, left):
        ax.annotate(f"{tot:.1f} s", (tot, yi), xytext=(3, 0), textcoords="offset points", va="center", fontsize=7)
    ax.set_xlim(0, left.max() * 1.15)
    ax.set_yticks(y, [b[0] for b in bars])
    ax.set_xlabel("wall time (s)")
    ax.grid(axis="y", visible=False)
    fig.legend(loc="outside right upper")
    fig.suptitle("Wall time by stage (summed over the tasks of each row)", fontsize=9, fontweight="bold")
    _save(fig, path)
    return True


def delta_sweep(path: Path, groups: Sequence[tuple[str, Sequence[tuple]]], fixed_delta: float = 0.5) -> bool:
    """Paper Fig. 7 from a δ sweep: ambiguous and total Gaussians after refinement vs δ.

    Args:
        groups: [(label, [(delta, ambiguous under its own δ, total, ambiguous under
            ``fixed_delta`` or None), ...])], one line per scene / object.
    """
    groups = [(g, sorted(pts)) for g, pts in groups if len(pts) >= 2]
    if not groups:
        return False
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(7.4, 2.7), layout="constrained")
    for k, (label, pts) in enumerate(groups):
        d = [p[0] for p in pts]
        c = PALETTE[k % len(PALETTE)] if len(groups) > 1 else REFERENCE_COLOR
        a1.plot(d, [p[1] for p in pts], "o-", color=c, ms=3.5,
                label="score < its own δ" + (f" ({label})" if len(groups) > 1 else ""))
        fixed = [(p[0], p[3]) for p in pts if p[3] is not None]
        if len(fixed) >= 2:
            a1.plot([f[0] for f in fixed], [f[1] for f in fixed], "o--", color=c, ms=3.5, mfc="white",
                    label=f"score < {fixed_delta:g}, last mask stage" + (f" ({label})" if len(groups) > 1 else ""))
        a2.plot(d, [p[2] for p in pts], "s-", color=c, ms=3.5, label=label)
    a1.set_title("ambiguous Gaussians at the end")
    a2.set_title("total Gaussians after refinement")
    a1.legend(loc="best", fontsize=7)
    for a in (a1, a2):
        a.set_xlabel("δ of the run")
    if len(groups) > 1:
        a2.legend(loc="best", fontsize=7)
    _save(fig, path)
    return True


def score_curves(path: Path, panels: Sequence[tuple[str, Sequence[tuple[str, np.ndarray]], Optional[float]]]
                 ) -> bool:
    """Per mask stage, how many Gaussians a threshold δ would call ambiguous (stage-mean
    score < δ), from the scores one run recorded; the run's own δ as a dashed line.

    Args:
        panels: [(title, [(stage label, scores [N] float)], delta used)].
    """
    panels = [p for p in panels if p[1]]
    if not panels:
        return False
    plt = _plt()
    n = min(len(panels), 4)
    fig, axes = plt.subplots(1, n, figsize=(2.9 * n + 0.6, 2.9), squeeze=False, layout="constrained")
    grid = np.linspace(0.0, 1.0, 201)
    cmap = plt.get_cmap("viridis")
    most = max(len(p[1]) for p in panels[:n])
    for ax, (title, curves, delta) in zip(axes[0], panels[:n]):
        for i, (label, s) in enumerate(curves):
            s = np.sort(np.asarray(s, np.float64))
            ax.plot(grid, np.searchsorted(s, grid, side="left"), color=cmap(i / max(1, most - 1)), lw=1.2,
                    label=label)
        if delta is not None:
            ax.axvline(delta, color="black", ls="--", lw=0.8)
            ax.text(delta, 0.97, f"δ = {delta:g} ", transform=ax.get_xaxis_transform(), fontsize=7,
                    va="top", ha="right")
        ax.set_title(title)
        ax.set_xlabel("threshold δ")
        # Most Gaussians score near 1 (unambiguous, or unseen): a log scale keeps the
        # few hundred near δ readable next to the jump at 1.
        ax.set_yscale("symlog", linthresh=10)
        ax.set_ylim(bottom=0)
        # plain tick labels: the default log formatter writes math text, which labels are not
        # parsed as (text.parse_math is off so that names with "$" stay text)
        from matplotlib.ticker import FuncFormatter

        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:,.0f}"))
    axes[0][0].set_ylabel("Gaussians with score < δ (log)")
    longest = max(panels[:n], key=lambda p: len(p[1]))
    handles = [plt.Line2D([], [], color=cmap(i / max(1, most - 1)), lw=1.2) for i in range(most)]
    fig.legend(handles, [c[0] for c in longest[1]], loc="outside right upper", fontsize=7)
    _save(fig, path)
    return True


TRAJECTORY_MARKERS = {"mask": "o", "texture": "s", "check": "*"}


def trajectory(path: Path, title: str, records: Sequence[dict], colors: dict[str, str]) -> bool:
    """Held-out IoU and boundary IoU after every stage of one scene's refinements (the
    records of :mod:`reports.trajectory`): one line per method / object, a marker per stage
    kind (mask ●, texture ■, the object-render check ★); x = 0 is the closed-form labels on
    the unrefined scene; dashed lines: the closed-form labels on each stage's geometry.
    ``colors`` must name every record's method (:func:`method_colors` over the run's methods
    and the records')."""
    records = [r for r in records if r.get("stages")]
    if not records:
        return False
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(9.2, 3.1), squeeze=False, layout="constrained")
    most = max(len(r["stages"]) for r in records)
    objects = sorted({r["object"] for r in records})
    styles = ("-", (0, (4, 1.5)), (0, (1, 1)), "-.")
    for r in records:
        c = colors[r["method"]]
        ls = styles[objects.index(r["object"]) % len(styles)]
        label = f"{r['method']} / {r['object']}"
        for ax, key in zip(axes[0], ("iou", "biou")):
            xs = list(range(len(r["stages"]) + 1))
            ys = [100 * r["start"][key]] + [100 * s[key] for s in r["stages"]]
            ax.plot(xs, ys, color=c, ls=ls, lw=1.1, label=label)
            for k, marker in TRAJECTORY_MARKERS.items():
                pts = [(i + 1, 100 * s[key]) for i, s in enumerate(r["stages"]) if s["kind"] == k]
                if pts:
                    ax.plot(*zip(*pts), ls="none", marker=marker, ms=4 if k != "check" else 7, color=c)
            if key == "biou":
                cf = [(i + 1, 100 * s["cf_biou"]) for i, s in enumerate(r["stages"]) if "cf_biou" in s]
                if cf:
                    ax.plot(*zip(*cf), color=c, ls=(0, (2, 2)), lw=0.7, alpha=0.7)
    for ax, name in zip(axes[0], ("IoU", "boundary IoU")):
        ax.set_xlabel("stage (0 = closed-form labels, unrefined scene)")
        ax.set_ylabel(f"held-out {name} (%)")
        ax.set_xlim(-0.3, most + 0.3)
        ax.set_xticks(range(most + 1))
    axes[0][0].set_title(title)
    handles = [plt.Line2D([], [], color="#444", ls="none", marker=m, ms=5, label=k) for k, m in TRAJECTORY_MARKERS.items()]
    lines, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(lines[:12] + handles, labels[:12] + [h.get_label() for h in handles], loc="outside right upper",
               fontsize=7)
    _save(fig, path)
    return True
