"""The report's methods: each method axis value described once (:class:`MethodInfo`: its
kind, the options that differ from the defaults, its role, the paper method it is, its Table 5
switches), and the reference method the others are compared with, taken from there."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from cobgs.configs import NOSPLIT_SWITCHES
from cobgs.evaluate.protocols import ORACLE_METHOD
from cobgs.refine.methods import REGISTRY

from . import paper
from .collect import RunData

KIND_LABELS = {name: m.label for name, m in REGISTRY.items()}  # (cobgs.refine.methods)
_SECTIONS = {name: m.sections for name, m in REGISTRY.items()}  # the params sections it reads
_EXTRA_STAGES = {name: m.extra_stage for name, m in REGISTRY.items() if m.extra_stage}


@dataclass
class MethodInfo:
    """A method axis value as the report names it.

    Attributes:
        name: the axis value.
        kind: the refine stage's ``method`` param (cobgs, nosplit, sa3d, flashsplat).
        options: params that differ from the refine stage's defaults (``bgtr=false``).
        role: "reference" (the COB-GS run the others are compared with), "variant"
            (another COB-GS configuration: ablation rows, δ sweeps) or "peer".
        paper: the paper's method it is (:func:`reports.paper.paper_method`), or None.
    """

    name: str
    kind: str = ""
    options: list[str] = field(default_factory=list)
    role: str = "peer"
    paper: Optional[tuple] = None
    raem: Optional[str] = None  # COB-GS's RAEM variant ("released", "paper", "off")
    # (BAGS, BGTR, RAEM on, object check) of a Table 5-style row (:func:`reports.paper.cobgs_switches`)
    switches: Optional[tuple] = None
    # a stage the method adds to COB-GS's ("NG-GS": cobgs.refine.methods.RefineMethod.extra_stage);
    # its switches are then those of the COB-GS it runs, and it is no faithful COB-GS row
    stage: str = ""

    @property
    def kind_label(self) -> str:
        return KIND_LABELS.get(self.kind, self.kind or "?")

    @property
    def config(self) -> str:
        return ", ".join(self.options) if self.options else "defaults"


def _flat(d, prefix: str = "") -> dict:
    out = {}
    for k, v in (d or {}).items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def _value_text(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return "none" if v is None else str(v)


def refine_defaults(workflow) -> dict:
    """The refine stage's default params as JSON (what an option differs from)."""
    from pipeline.params import to_json

    stage = workflow.graph.producer.get("refined")
    if stage is None:
        return {}
    return to_json(workflow.stages[stage].params())


# The no-split row forces COB-GS's switches off whatever the params say (cobgs.configs.NOSPLIT_SWITCHES)
_FORCED = {"nosplit": tuple(f"cobgs.{k}" for k in NOSPLIT_SWITCHES)}


def options_of(kind: str, params: Optional[dict], defaults: dict) -> list[str]:
    if not params:
        return []
    sections = _SECTIONS.get(kind, ())
    got, base = _flat(params), _flat(defaults)
    keep = [k for k in got if k not in ("method",) + _FORCED.get(kind, ())
            and (k.split(".")[0] in sections or "." not in k)]
    return [f"{k.split('.', 1)[-1]}={_value_text(got[k])}" for k in keep if got[k] != base.get(k)]


def method_infos(data: RunData) -> dict[str, MethodInfo]:
    defaults = refine_defaults(data.workflow)
    infos = {m: MethodInfo(m) for m in data.methods}
    seen: dict[str, set] = {}
    for r in data.results:
        info = infos.setdefault(r.method, MethodInfo(r.method))
        if r.refine_params is None:
            continue
        opts = options_of(r.method_kind, r.refine_params, defaults)
        if r.method not in seen:
            info.kind, info.options = r.method_kind, opts
            info.paper = paper.paper_method(r.method_kind, r.refine_params)
            info.stage = _EXTRA_STAGES.get(r.method_kind, "")
            base = "cobgs" if info.stage else r.method_kind  # the COB-GS a stage is added to
            info.switches = ((False, False, False, "off") if r.method_kind == "nosplit"
                             else paper.cobgs_switches(base, r.refine_params))
            if base == "cobgs":
                info.raem = str(((r.refine_params.get("cobgs") or {}).get("raem")
                                 or (defaults.get("cobgs") or {}).get("raem") or "released"))
        seen.setdefault(r.method, set()).add(tuple(sorted(opts)))  # the same options in any order
    for m, variants in seen.items():
        if len(variants) > 1:  # per-scene overrides: say so rather than pick one
            infos[m].options = infos[m].options + ["(varies by scene)"]
            infos[m].paper = infos[m].switches = None
    if ORACLE_METHOD in infos:
        picks = sorted({str((r.row or {}).get("oracle_choice")) for r in data.results if r.method == ORACLE_METHOD})
        infos[ORACLE_METHOD] = MethodInfo(ORACLE_METHOD, kind="flashsplat", options=[
            "best background bias per scene, chosen on the held-out GT (an oracle in its favour; "
            f"picked: {', '.join(picks)})"])
    ref = reference_method(infos)
    for m, info in infos.items():
        info.role = "reference" if m == ref else ("variant" if info.kind in ("cobgs", "nosplit") else "peer")
    return infos


def reference_method(infos: dict[str, MethodInfo]) -> Optional[str]:
    """The COB-GS item with default options, else the first COB-GS item, else the first."""
    for pick in (lambda i: i.kind == "cobgs" and not i.options, lambda i: i.kind == "cobgs", lambda i: True):
        for m, info in infos.items():
            if info.kind and pick(info):
                return m
    return next(iter(infos), None)




def reference_of(infos: dict[str, MethodInfo]) -> Optional[str]:
    """The reference method :func:`method_infos` chose (its ``role``), or None."""
    return next((m for m, info in infos.items() if info.role == "reference"), None)
