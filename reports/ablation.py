"""Paper Tables 5 and 4 at benchmark scale: the switch rows, their faithful twins, PSNR per
RAEM variant."""

from __future__ import annotations

from typing import Optional


from .fmt import finite

from .methods import MethodInfo


# -- paper Tables 5 and 4 at benchmark scale ---------------------------------------------
def _switch_order(sw: tuple) -> tuple:
    """none, BAGS, BAGS + BGTR, all three (the paper's rows); other combinations by count."""
    return (sum(sw), tuple(not x for x in sw))


_RAEM_ORDER = {"off": 0, "released": 1, "paper": 2}


def _switches(info: Optional[MethodInfo]) -> Optional[tuple]:
    """(BAGS, BGTR, RAEM) of a Table 5 row: COB-GS and its switch ablations, no-split = none
    (with or without the object-render check: :func:`_check`)."""
    if info is None or info.switches is None:
        return None
    return tuple(info.switches[:3])


def _check(info: Optional[MethodInfo]) -> str:
    """The object-render check of a Table 5-style row ("off" / "visible")."""
    return str(info.switches[3]) if info is not None and info.switches is not None else "off"


def faithful_twins(infos: dict, method: Optional[str]) -> list[str]:
    """The faithful COB-GS rows a checked row is the variant of (the rule, written once: the
    same switches, the same RAEM, object check off, no added stage; docs/method.md §7: our
    variant beside the faithful). Empty for a row without the check."""
    mine = infos.get(method) if method else None
    if mine is None or mine.switches is None or _check(mine) == "off":
        return []
    return [m for m, i in infos.items() if m != method and i.switches is not None and _check(i) == "off"
            and not i.stage and tuple(i.switches[:3]) == tuple(mine.switches[:3]) and i.raem == mine.raem]


def ablation_records(by_scene: list[dict], infos: dict) -> list[dict]:
    """Paper Table 5 per scene (and mask route): the rows that switch BAGS, BGTR and RAEM on
    and off (the no-split row = none of them), in the paper's order, each RAEM variant apart.

    Rows are the per scene x method records (:func:`scene_method_records`), so the numbers
    are the same as in the results table; only the selection, order and switch columns are
    new. Best values are marked within a scene and route.
    """
    order = {g: i for i, g in enumerate(dict.fromkeys(r["_group"] for r in by_scene))}
    out = []
    for rec in by_scene:
        info = infos.get(rec["method"])
        sw = _switches(info)
        if sw is None:
            continue
        raem = "off" if not sw[2] else (info.raem or "released")
        check = _check(info)
        row = dict(rec)
        twins = faithful_twins(infos, rec["method"])
        row.update(bags="✓" if sw[0] else "", bgtr="✓" if sw[1] else "", raem=raem,
                   check="" if check == "off" else check, stage=info.stage, role=info.role,
                   twin=twins[0] if twins else "",
                   _sort=(order[rec["_group"]], _switch_order(sw), _RAEM_ORDER.get(raem, 3), check != "off",
                          info.stage, rec["method"]))
        row["_text"] = dict(rec.get("_text") or {})
        out.append(row)
    out.sort(key=lambda r: r["_sort"])
    return out if len({r["_sort"][1] for r in out}) >= 2 else []


def psnr_records(by_scene: list[dict], infos: dict, ref: Optional[str]) -> list[dict]:
    """Paper Table 4 per scene (and mask route): held-out PSNR of the vanilla scene, after the
    mask stages alone (BAGS, no BGTR: "M.O"), after mask + texture stages before RAEM (the
    reference's scene before its final pruning: "M.O+T.O", the paper's measurement), and after
    each RAEM variant. Means over the scene's objects, like every per-scene number.

    The paper's "texture only" column (texture stages without splitting) has no row in
    our ablations: left out rather than approximated.
    """
    groups: dict[str, list[dict]] = {}
    for rec in by_scene:
        groups.setdefault(rec["_group"], []).append(rec)
    out = []
    for g, recs in groups.items():
        by_m = {r["method"]: r for r in recs}
        row: dict = {"scene": recs[0]["scene"], "masks": recs[0].get("masks"), "_title": {}, "_text": {}}
        vanilla = next((finite(r.get("psnr_vanilla")) for r in recs if finite(r.get("psnr_vanilla")) is not None),
                       None)
        row["vanilla"] = vanilla
        for r in recs:
            sw = _switches(infos.get(r["method"]))
            if sw == (True, False, False) and "mask_only" not in row:
                row["mask_only"], row["_title"]["mask_only"] = finite(r.get("psnr")), f"{r['method']}"
        mine = by_m.get(ref) if ref else None
        if mine is not None:
            row["joint"] = finite(mine.get("psnr_before_raem"))
            row["_title"]["joint"] = f"{ref}, its scene before RAEM"
        for r in recs:
            info = infos.get(r["method"])
            if _switches(info) == (True, True, True) and info.raem and not info.stage:
                key = f"raem_{info.raem}"
                if key not in row or r["method"] == ref:
                    row[key], row["_title"][key] = finite(r.get("psnr")), r["method"]
        if vanilla is None or all(row.get(k) is None for k in ("mask_only", "joint")):
            continue
        for k in ("mask_only", "joint", "raem_released", "raem_paper"):
            if row.get(k) is not None:
                row[f"d_{k}"] = row[k] - vanilla
        if row.get("joint") is not None:
            ok = row["joint"] >= vanilla - 0.1
            row["target"] = "met" if ok else "not met"
            row["_class"] = {"target": ["ok" if ok else "failed"]}
            row["_title"]["target"] = f"before-RAEM PSNR {row['joint'] - vanilla:+.3f} dB vs vanilla (bar −0.1 dB)"
        out.append(row)
    return out
