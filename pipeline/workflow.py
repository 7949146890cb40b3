"""Workflow files: TOML (stdlib :mod:`tomllib`) naming items, params and settings.

Schema (every table optional except ``[axes]`` when a stage runs per item)::

    [workflow]
    name = "demo"                     # default: the file's stem
    description = "..."
    stages = ["report"]               # targets; their upstream stages are included.
                                      # Default: every registered stage.
    nested = { object = "scene" }     # axis -> parent axis (values declared per parent)

    [settings]                        # workflow-wide, readable as ctx.settings
    device = "cpu"                    # "cpu" | "cuda" | "cuda:1"; --set device=cuda

    [params.train]                    # per-stage params for every item
    iterations = 7000

    [axes.scene.lego]                 # axis "scene", value "lego"
    path = "../data/lego"             # attributes (typed by an axis schema if registered)
    train = { iterations = 3000 }     # a table named after a stage: overrides for this item

    [axes.method.cobgs_full]
    [axes.method.no_bags]
    refine.split = false              # dotted keys are tables too

    [axes.method.delta_03]
    only = "scene=lego/object=crate"  # takes part in these items only (a list of patterns, or
                                      # one; every part names its axis). Not hashed: it says
                                      # which items exist, not what they compute.

Precedence, lowest first: stage defaults, ``[params.<stage>]``, item overrides (in axis
order, so a method's override beats its scene's), ``--set stage.param=value``. A value may
reference environment variables as ``${NAME}`` or ``${NAME:-default}``; an unset one fails
the load with the key that needs it (``$${`` is a literal ``${``). Relative ``Path`` values resolve against the workflow
file's folder (``--set`` values against the current directory).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import re
import stat
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Sequence

from . import params as P
from .errors import PipelineError, WorkflowError, unknown_key_hint
from .graph import Graph
from .hashing import FingerprintMemo, stat_fingerprint
from .items import MAX_VALUE_BYTES, VALUE_RE, Axes, Axis, Item, ItemFilter, check_value_name, invisible_chars
from .registry import Registry
from .stage import NAME_RE, Stage
from .values import Settings

TOP_KEYS = ("workflow", "settings", "params", "axes")
WORKFLOW_KEYS = ("name", "description", "stages", "nested")
#: Largest workflow file read (the shipped ones are a few KiB).
MAX_WORKFLOW_BYTES = 16 << 20
#: ``${NAME}`` / ``${NAME:-default}``; ``$${`` is a literal ``${`` (a folder named so: `cobgs new`
#: writes its paths that way).
_ENV_RE = re.compile(r"\$\$\{|\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")


@dataclass(frozen=True)
class ResolvedParams:
    """A stage's params for one item, with their canonical JSON; ``key_json`` is the part
    that enters the cache key (all of it unless the stage declares ``key_params``)."""

    value: Any
    json: Mapping[str, Any]
    key_json: Optional[Mapping[str, Any]] = None

    def __post_init__(self) -> None:
        if self.key_json is None:
            object.__setattr__(self, "key_json", self.json)


class Workflow:
    """A loaded, validated workflow. Build it with :func:`load_workflow`."""

    def __init__(self, *, path: Path, name: str, description: str, settings: Settings,
                 axes: Axes, graph: Graph, targets: tuple[str, ...],
                 levels: Mapping[str, tuple[str, ...]], stage_layers: Mapping[str, P.Layer],
                 item_layers: Mapping[tuple[str, str], Mapping[str, P.Layer]],
                 cli_layers: Mapping[str, P.Layer], key_attrs: Mapping[str, tuple[str, ...]],
                 registry: Registry):
        self.path, self.name, self.description = path, name, description
        self.settings, self.axes, self.graph, self.targets = settings, axes, graph, targets
        self.levels = dict(levels)  # stage -> level in workflow axis order
        self._stage_layers, self._item_layers = stage_layers, item_layers
        self._cli_layers, self._key_attrs = cli_layers, key_attrs
        self.registry = registry
        self._params_cache: dict[tuple, ResolvedParams] = {}
        self._fingerprints: dict[str, str] = {}
        self._verify: set[str] = set()  # external paths whose content is re-read (verify_data)
        self._verify_all = False
        self._contents: dict = {}  # content fingerprints read by this command (FingerprintMemo.key)
        #: set by the run / inspection against a cache (:meth:`use_cache`)
        self.fingerprint_memo: Optional[FingerprintMemo] = None

    @property
    def id(self) -> str:
        """Stable id of this workflow file (its absolute path), for per-slot history."""
        return hashlib.sha256(os.fspath(self.path).encode()).hexdigest()[:16]

    @property
    def stages(self) -> dict[str, Stage]:
        return self.graph.stages

    def params_for(self, stage: str, item: Item) -> ResolvedParams:
        """The params of ``stage`` for ``item``, layered and typed (memoised)."""
        layers = self._layers(stage, item)
        memo = tuple(id(layer) for layer in layers)
        hit = self._params_cache.get((stage, memo))
        if hit is None:
            cls = self.stages[stage].params
            value = P.build(cls, layers, owner=f"stage {stage!r}")
            full = P.to_json(value)
            key_fn = self.stages[stage].key_params
            hit = ResolvedParams(value, full, key_fn(value, full) if key_fn is not None else full)
            self._params_cache[(stage, memo)] = hit
        return hit

    def locate(self, stage: str, item: Item, message: str) -> tuple[Optional[str], Optional[str]]:
        """Where the value a check refused was set: ``(source, dotted key)`` of the first
        param that ``message`` names among those the layers of ``stage`` x ``item`` set
        (the last layer setting it wins); ``(None, None)`` when it names none."""
        leaves = P.set_values(self.stages[stage].params, self._layers(stage, item))
        hit = P.first_named(((path[-1], (layer.source, key)) for path, (_, layer, key) in leaves.items()),
                            message)
        return hit if hit is not None else (None, None)

    def _layers(self, stage: str, item: Item) -> list[P.Layer]:
        """The value layers of ``stage`` for ``item``, lowest precedence first: the
        workflow's table, each axis value's overrides (in axis order), then ``--set``."""
        layers: list[P.Layer] = []
        if stage in self._stage_layers:
            layers.append(self._stage_layers[stage])
        for pair in item.pairs:
            layer = self._item_layers.get(self.axes.slot(pair[0], item.pairs), {}).get(stage)
            if layer is not None:
                layers.append(layer)
        if stage in self._cli_layers:
            layers.append(self._cli_layers[stage])
        return layers

    def _applies(self, axis: str, attr: str, stage: Optional[str]) -> bool:
        """Whether attribute ``attr`` enters the keys of ``stage`` (None: every stage's):
        an attribute whose field names ``key_stages`` enters only theirs."""
        staged = self._key_attrs.get("__staged__", {}).get((axis, attr))
        return staged is None or stage is None or stage in staged[0]

    def use_cache(self, cache_root: os.PathLike | str, writable: bool) -> None:
        """Key external data through the cache's fingerprint memo
        (:class:`~pipeline.hashing.FingerprintMemo`), so that the same bytes under new file
        times (a copy, a re-mount) keep their keys. Every run and inspection of a cache
        calls this first; a writable memo (a run) records what it hashes."""
        root = Path(os.path.abspath(os.fspath(cache_root))) / "fingerprints"
        memo = self.fingerprint_memo
        if memo is None or memo.folder != root or (writable and not memo.writable):
            self.fingerprint_memo = FingerprintMemo(root, writable)
            self._fingerprints.clear()

    def data_paths(self, item: Item, params: Any, stage: Optional[str] = None) -> dict[str, Path]:
        """The external files and folders a task reads: every ``Path`` value of the item's key
        attributes (those that enter ``stage``'s key) and of ``params``, by where it is set."""
        found: dict[str, Path] = {}
        for axis, attrs in item.attrs.items():
            keep = self._key_attrs.get(axis)
            for name, value in _paths(attrs, f"{axis}"):
                if (keep is None or name.split(".")[1] in keep) and self._applies(axis, name.split(".")[1], stage):
                    found[name] = value
        found.update(_paths(params, "params"))
        return dict(sorted(found.items()))

    def data_fingerprints(self, item: Item, params: Any, stage: Optional[str] = None) -> dict[str, str]:
        """Fingerprints (:func:`~pipeline.hashing.stat_fingerprint`) of the files and folders
        that the item's key attributes and ``params`` name (every ``Path`` value), keyed
        by where the path is set: external data read by a task enter its cache key, so a
        changed dataset, mask folder or model folder is recomputed, not served stale.
        Memoised per loaded workflow (one walk per folder per command); paths given to
        :meth:`verify_data` are keyed by their content as read now."""
        out = {}
        for name, path in self.data_paths(item, params, stage).items():
            k = os.fspath(path)
            if k not in self._fingerprints:
                memo = self.fingerprint_memo
                verify = self._verify_all or k in self._verify
                self._fingerprints[k] = (memo.key(Path(k), verify=verify, contents=self._contents)
                                         if memo is not None else stat_fingerprint(Path(k)))
            out[name] = self._fingerprints[k]
        return out

    def verify_data(self, paths: Optional[Iterable[os.PathLike | str]] = None) -> None:
        """Re-read the content of these external paths (None: of every one) instead of
        trusting their size and modification time (``cobgs run --force STAGE``,
        ``--verify-data``, ``cobgs status --verify-data``): an edit that kept both then
        changes the keys of every task that reads the data. Takes effect for fingerprints
        computed after the call. Data over ``FingerprintMemo.MAX_BYTES`` stay keyed by their
        stat fingerprint."""
        if paths is None:
            self._verify_all = True
            self._fingerprints.clear()
            return
        for p in paths:
            k = os.fspath(p)
            self._verify.add(k)
            self._fingerprints.pop(k, None)

    def key_attrs(self, item: Item, stage: Optional[str] = None) -> dict[str, Any]:
        """The attributes of ``item`` that enter the cache keys of ``stage``, as JSON. An
        attribute read by some stages only (``key_stages``) shows its default to the others,
        so that their keys are those of the same item without it."""
        out: dict[str, Any] = {}
        staged = self._key_attrs.get("__staged__", {})
        for axis, attrs in item.attrs.items():
            data = P.to_json(attrs)
            keep = self._key_attrs.get(axis)
            if keep is not None and isinstance(data, dict):
                data = {k: v for k, v in data.items() if k in keep}
            if isinstance(data, dict):
                for k in list(data):
                    if not self._applies(axis, k, stage):
                        data[k] = P.to_json(staged[(axis, k)][1])
            out[axis] = data
        return out


def _paths(value: Any, prefix: str) -> list[tuple[str, Path]]:
    """``(dotted name, path)`` of every ``Path`` in a (nested) params / attributes dataclass."""
    out: list[tuple[str, Path]] = []
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            out += _paths(getattr(value, f.name), f"{prefix}.{f.name}")
    elif isinstance(value, Path):
        out.append((prefix, value))
    return out


def expand_env(value: Any, source: str, key: str, environ: Mapping[str, str],
               missing: Optional[dict] = None) -> Any:
    """``${NAME}`` / ``${NAME:-default}`` expanded in every string of ``value``. Unset
    variables without a default are all reported at once (one error naming each variable
    and the keys that need it), not one per attempt."""
    top = missing is None
    missing = {} if top else missing
    out = _expand(value, key, environ, missing)
    if top and missing:
        names = sorted(missing)
        raise WorkflowError(
            "; ".join(f"environment variable {n} is not set ({', '.join(missing[n][:3])}"
                      f"{' ...' if len(missing[n]) > 3 else ''} need{'s' if len(missing[n]) == 1 else ''} it)"
                      for n in names)
            + "; set " + ("it" if len(names) == 1 else "them") + ", e.g. `export "
            + " ".join(f"{n}=..." for n in names) + "`", source)
    return out


def _expand(value: Any, key: str, environ: Mapping[str, str], missing: dict) -> Any:
    if isinstance(value, str):
        def sub(match: re.Match) -> str:
            if match.group(0) == "$${":
                return "${"
            name, default = match.group(1), match.group(2)
            got = environ.get(name)
            if got:
                return got
            if default is not None:
                return default
            missing.setdefault(name, []).append(key)
            return match.group(0)
        return _ENV_RE.sub(sub, value)
    if isinstance(value, dict):
        return {k: _expand(v, f"{key}.{k}" if key else k, environ, missing) for k, v in value.items()}
    if isinstance(value, list):
        return [_expand(v, f"{key}[{i}]", environ, missing) for i, v in enumerate(value)]
    return value


def _table(value: Any, source: str, key: str) -> dict:
    if not isinstance(value, dict):
        raise WorkflowError(f"expected a table, got {value!r}", source, key)
    return value


def _check_keys(table: Mapping, allowed: Sequence[str], source: str, prefix: str) -> None:
    for k in table:
        if k not in allowed:
            raise WorkflowError(f"unknown key {k!r}" + unknown_key_hint(k, allowed), source,
                                f"{prefix}.{k}" if prefix else k)


def _split_sets(sets: Sequence[str]) -> list[tuple[str, str]]:
    out = []
    for text in sets:
        key, eq, value = text.partition("=")
        if not eq or not key.strip():
            raise WorkflowError(f"expected KEY=VALUE (e.g. train.iterations=100 or "
                                f"device=cuda), got {text!r}", "--set")
        out.append((key.strip(), value))
    return out


def _assign(raw: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = raw
    for part in parts[:-1]:
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise WorkflowError(f"cannot set inside {part!r}, which is not a table", "--set",
                                dotted)
        node = nxt
    node[parts[-1]] = value


def load_workflow(path: os.PathLike | str, registry: Registry, sets: Sequence[str] = (),
                  environ: Optional[Mapping[str, str]] = None,
                  cwd: Optional[Path] = None) -> Workflow:
    """Read, validate and type a workflow file.

    Args:
        path: the TOML file.
        registry: the stages (and axis schemas) it may use.
        sets: ``KEY=VALUE`` overrides: ``device=cuda`` / ``settings.device=cuda``,
            ``STAGE.PARAM[.SUB]=V`` (or ``params.STAGE.PARAM=V``), and
            ``axes.AXIS.VALUE.KEY=V`` for item attributes and overrides.
        environ: environment for ``${NAME}`` (default :data:`os.environ`).
        cwd: folder relative ``--set`` paths resolve against (default: current directory).

    Raises:
        WorkflowError: naming the file (or ``--set``) and the key at fault.
    """
    path = Path(os.path.abspath(os.fspath(path)))
    source = os.fspath(path)
    environ = os.environ if environ is None else environ
    cwd = Path(os.path.abspath(cwd or os.getcwd()))
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):  # /dev/zero would be read forever, a FIFO would block
            raise WorkflowError("not a regular file (a device, a pipe or a folder?); give the workflow's "
                                "TOML file", source)
        if st.st_size > MAX_WORKFLOW_BYTES:
            raise WorkflowError(f"{st.st_size / 2**20:.1f} MiB: more than the {MAX_WORKFLOW_BYTES >> 20} MiB a "
                                "workflow file may have (it is a few KiB of TOML)", source)
        data = path.read_bytes()
    except FileNotFoundError:
        raise WorkflowError("workflow file not found", source) from None
    except OSError as exc:
        raise WorkflowError(f"cannot read the workflow file: {exc}", source) from None
    if data.startswith(b"\xef\xbb\xbf"):  # a UTF-8 byte-order mark (some Windows editors add one)
        data = data[3:]
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise WorkflowError(f"not UTF-8 text: byte 0x{data[exc.start]:02x} on line {line} (TOML files are "
                            "UTF-8; save it as UTF-8)", source) from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise WorkflowError(f"invalid TOML: {exc}", source) from None
    except ValueError as exc:  # an integer past Python's digit limit (no param's range holds it)
        raise WorkflowError(f"invalid value: {str(exc).split(';')[0]} (an integer no param can hold)",
                            source) from None
    except RecursionError:
        raise WorkflowError("invalid TOML: arrays or tables nested too deep to read", source) from None
    _check_keys(raw, TOP_KEYS, source, "")
    try:
        graph_all = registry.graph()
    except PipelineError as exc:
        raise WorkflowError(f"the stage registry is invalid: {exc}", source) from None

    # --set: settings and stage params become the top layer; axes.* edit the raw file.
    cli_settings: dict[str, Any] = {}
    cli_stage: dict[str, dict] = {}
    for key, value in _split_sets(sets):
        if key == "device" or key.startswith("settings."):
            _assign(cli_settings, key.removeprefix("settings."), value)
        elif key.startswith("axes."):
            if key.count(".") < 3:
                raise WorkflowError("expected axes.AXIS.VALUE.KEY=VALUE", "--set", key)
            _assign(raw, key, P.parse_cli_value(value))
        else:
            stage_key = key.removeprefix("params.")
            stage, dot, rest = stage_key.partition(".")
            if not dot or not rest:
                raise WorkflowError("expected STAGE.PARAM=VALUE, device=VALUE or "
                                    "axes.AXIS.VALUE.KEY=VALUE", "--set", key)
            if stage not in graph_all.stages:
                raise WorkflowError(f"unknown stage {stage!r}"
                                    + unknown_key_hint(stage, graph_all.stages), "--set", key)
            _assign(cli_stage.setdefault(stage, {}), rest, value)

    raw = expand_env(raw, source, "", environ)
    base = path.parent

    wf = _table(raw.get("workflow", {}), source, "workflow")
    _check_keys(wf, WORKFLOW_KEYS, source, "workflow")
    name = wf.get("name", path.stem)
    description = wf.get("description", "")
    for k, v in (("name", name), ("description", description)):
        if not isinstance(v, str):
            raise WorkflowError(f"expected a string, got {v!r}", source, f"workflow.{k}")
    where = "workflow.name" if "name" in wf else "(the file name)"
    if not VALUE_RE.match(name) or invisible_chars(name):  # the default report folder is runs/reports/<name>
        raise WorkflowError(f"workflow name {name!r} may not be empty, start with a space or '.', "
                            "end with a space, or contain '/', '\\', ',', '=', a control character or an "
                            "invisible formatting character (it names the report folder)", source, where)
    if len(name.encode("utf-8")) > MAX_VALUE_BYTES:
        raise WorkflowError(f"workflow name {name[:40]!r}... is {len(name.encode('utf-8'))} bytes long; at most "
                            f"{MAX_VALUE_BYTES} (it names the report folder: runs/reports/<name>)", source, where)

    settings = P.build(Settings, [P.Layer(_table(raw.get("settings", {}), source, "settings"),
                                          source, base, prefix="settings"),
                                  P.Layer(cli_settings, "--set", cwd, cli=True)],
                       owner=f"{source}: settings")

    targets = wf.get("stages")
    if targets is None:
        targets = list(graph_all.stages)
    if not isinstance(targets, list) or not all(isinstance(t, str) for t in targets):
        raise WorkflowError(f"expected a list of stage names, got {targets!r}", source,
                            "workflow.stages")
    for t in targets:
        if t not in graph_all.stages:
            raise WorkflowError(f"unknown stage {t!r}" + unknown_key_hint(t, graph_all.stages),
                                source, "workflow.stages")
    graph = graph_all.subgraph(targets) if targets else Graph([])
    for stage in cli_stage:
        if stage not in graph.stages:
            raise WorkflowError(f"stage {stage!r} is not part of this workflow (stages: "
                                f"{list(graph.order)})", "--set", stage)

    nested = _table(wf.get("nested", {}), source, "workflow.nested")
    axes_raw = _table(raw.get("axes", {}), source, "axes")
    axes, item_layers, key_attrs = _load_axes(axes_raw, nested, graph, registry, source, base)
    _check_reserved(axes_raw, registry, source)

    levels = {}
    for stage_name in graph.order:
        levels[stage_name] = axes.normalize_level(graph.stages[stage_name].level,
                                                  f"stage {stage_name!r}", source)
    for (axis, value), overrides in item_layers.items():
        for stage_name in overrides:
            if axis not in levels[stage_name]:
                raise WorkflowError(
                    f"stage {stage_name!r} runs per {levels[stage_name] or 'workflow'}, not per "
                    f"{axis!r}, so a {axis!r} value cannot override its params", source,
                    f"axes.{axis}.{value}.{stage_name}")

    params_raw = _table(raw.get("params", {}), source, "params")
    stage_layers = {}
    for stage_name, table in params_raw.items():
        if stage_name not in graph.stages:
            where = ("is not part of this workflow (its stages: " + ", ".join(graph.order) + ")"
                     if stage_name in graph_all.stages else "is not a known stage"
                     + unknown_key_hint(stage_name, graph.stages))
            raise WorkflowError(f"stage {stage_name!r} {where}", source, f"params.{stage_name}")
        stage_layers[stage_name] = P.Layer(_table(table, source, f"params.{stage_name}"),
                                           source, base, prefix=f"params.{stage_name}")
    cli_layers = {s: P.Layer(v, "--set", cwd, cli=True, prefix=s) for s, v in cli_stage.items()}

    workflow = Workflow(path=path, name=name, description=description, settings=settings,
                        axes=axes, graph=graph, targets=tuple(targets), levels=levels,
                        stage_layers=stage_layers, item_layers=item_layers,
                        cli_layers=cli_layers, key_attrs=key_attrs, registry=registry)
    # Type every layer now, so a bad key fails the load rather than the 40th task.
    for stage_name in graph.order:
        layers = [stage_layers.get(stage_name), cli_layers.get(stage_name)]
        layers += [ov[stage_name] for ov in item_layers.values() if stage_name in ov]
        for layer in filter(None, layers):
            P.check(graph.stages[stage_name].params, layer)
    return workflow


def _load_axes(axes_raw: dict, nested: dict, graph: Graph, registry: Registry, source: str,
               base: Path) -> tuple[Axes, dict, dict]:
    item_layers: dict[tuple[str, str], dict[str, P.Layer]] = {}
    key_attrs: dict[str, tuple[str, ...]] = {}
    staged = key_attrs.setdefault("__staged__", {})  # (axis, attr) -> (stages, default)
    axes: list[Axis] = []
    only_raw: dict[tuple[str, str], Any] = {}
    shares_raw: dict[tuple[str, str], Any] = {}
    for child, parent in nested.items():
        if child not in axes_raw or not isinstance(parent, str) or parent not in axes_raw:
            raise WorkflowError(f"expected an axis nested in a declared axis, got {child!r} in "
                                f"{parent!r} (axes: {list(axes_raw)})", source,
                                f"workflow.nested.{child}")
        if list(axes_raw).index(parent) > list(axes_raw).index(child):
            raise WorkflowError(f"axis {child!r} is nested in {parent!r}, so [axes.{parent}] "
                                "must come first in the file", source, f"axes.{child}")
    for axis_name, table in axes_raw.items():
        if not NAME_RE.match(axis_name):
            raise WorkflowError(f"axis names must match {NAME_RE.pattern}", source,
                                f"axes.{axis_name}")
        table = _table(table, source, f"axes.{axis_name}")
        if not table:
            raise WorkflowError("axis has no values", source, f"axes.{axis_name}")
        schema = registry.axis_schemas.get(axis_name)
        if schema is not None:
            key_attrs[axis_name] = tuple(f.name for f in dataclasses.fields(schema)
                                         if f.metadata.get("cache_key", True))
            for f in dataclasses.fields(schema):
                if f.metadata.get("key_stages"):
                    staged[(axis_name, f.name)] = (tuple(f.metadata["key_stages"]), f.default)
        parent = nested.get(axis_name)
        if parent is None:
            values = {}
            for value, vt in table.items():
                vt = _with_preset(registry, axis_name, vt, source, f"axes.{axis_name}.{value}")
                values[value] = _load_value(axis_name, value, vt, f"axes.{axis_name}.{value}",
                                            schema, graph, source, base, item_layers, only_raw, shares_raw)
            axes.append(Axis(axis_name, values))
        else:
            parent_values = next(a for a in axes if a.name == parent).values
            per_parent: dict[str, dict[str, Any]] = {}
            for pv, sub in table.items():
                if pv not in parent_values:
                    raise WorkflowError(f"{pv!r} is not a value of axis {parent!r} (values: "
                                        f"{list(parent_values)})", source, f"axes.{axis_name}.{pv}")
                sub = _table(sub, source, f"axes.{axis_name}.{pv}")
                per_parent[pv] = {
                    value: _load_value(axis_name, value,
                                       _with_preset(registry, axis_name, vt, source, f"axes.{axis_name}.{pv}.{value}"),
                                       f"axes.{axis_name}.{pv}.{value}",
                                       schema, graph, source, base, item_layers, only_raw, shares_raw, slot=pv)
                    for value, vt in sub.items()}
            axes.append(Axis(axis_name, per_parent, parent=parent))
    plain = Axes(axes)
    only = {slot: _parse_only(text, slot, plain, source) for slot, text in only_raw.items()}
    shares = _check_shares(shares_raw, plain, source)
    return Axes(axes, only, shares), item_layers, key_attrs


def _check_shares(shares_raw: dict, axes: Axes, source: str) -> dict[tuple[str, str], str]:
    """``shares = "VALUE"``: another value of the same flat axis, itself sharing nothing."""
    out = {}
    for (axis, slot), target in shares_raw.items():
        key = f"axes.{axis}.{slot.replace('/', '.')}.shares"
        if axes[axis].parent is not None:
            raise WorkflowError(f"'shares' is for values of a flat axis; {axis!r} is nested in "
                                f"{axes[axis].parent!r}", source, key)
        names = axes[axis].names()
        if not isinstance(target, str) or target not in names or target == slot:
            raise WorkflowError(f"expected the name of another {axis} value, got {target!r} "
                                f"(values: {[n for n in names if n != slot]})", source, key)
        if (axis, target) in shares_raw:
            raise WorkflowError(f"{target!r} itself shares {shares_raw[(axis, target)]!r}; name that "
                                "value instead (no chains)", source, key)
        out[(axis, slot)] = target
    return out


def _parse_only(text: Any, slot: tuple[str, str], axes: Axes, source: str) -> ItemFilter:
    """``only = "scene=forward/object=crate"`` (or a list of such patterns): where a value
    takes part. Every part names its axis; the patterns must select at least one item
    holding the value (a typo would otherwise silently drop it from the run)."""
    axis, value = slot
    key = f"axes.{axis}.{value.replace('/', '.')}.only"
    patterns = [text] if isinstance(text, str) else text
    if not isinstance(patterns, list) or not patterns or not all(isinstance(t, str) for t in patterns):
        raise WorkflowError(f"expected an item pattern such as \"scene=lego/object=crate\" or a list of "
                            f"them, got {text!r}", source, key)
    try:
        filt = ItemFilter.parse(",".join(patterns), axes)
    except WorkflowError as exc:
        raise WorkflowError(str(exc), source, key) from None
    for pattern in filt.patterns:
        bare = [g for a, g in pattern if a is None]
        if bare:
            raise WorkflowError(f"each part of an 'only' pattern names its axis (axis=glob); "
                                f"{bare[0]!r} does not (axes: {list(axes.order)})", source, key)
    holding = [i for i in axes.all_items() if axes.slot(axis, i.pairs) == slot]
    if not any(filt.selects_full(i) for i in holding):
        raise WorkflowError(f"{patterns!r} selects no item holding {axis} {value.split('/')[-1]!r}; "
                            "it would never run", source, key)
    return filt


def _check_reserved(axes_raw: Any, registry: Registry, source: str) -> None:
    """Axis values become folder names beside the files the program writes (an export's
    ``<scene>/train.json``, ``summary.json``): a value named like one of those files is
    refused here, not when the export writes a folder where the file is."""
    reserved = getattr(registry, "reserved_names", frozenset())
    if not reserved or not isinstance(axes_raw, dict):
        return
    for axis, values in axes_raw.items():
        if not isinstance(values, dict):
            continue
        names = list(values)
        if any(isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()) for v in values.values()):
            names += [n for v in values.values() if isinstance(v, dict) for n in v]  # (nested axes)
        for name in names:
            if isinstance(name, str) and name.lower() in reserved:
                raise WorkflowError(f"value name {name!r} is the name of a file cobgs writes beside the value's "
                                    f"folder (e.g. in an export); choose another name", source, f"axes.{axis}.{name}")


def _merged(under: Mapping, over: Mapping) -> dict:
    """``over`` laid on ``under``: tables merged key by key, any other value replaced."""
    out = dict(under)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def _with_preset(registry: Registry, axis: str, table: Any, source: str, key: str) -> Any:
    """An axis value's table with its ``preset = "NAME"`` resolved: the program's preset of that
    name for this axis (``Registry.presets``) with the value's own keys laid over it. The preset's
    name is not hashed: the tasks of ``preset = "x"`` and of the same keys written out have the
    same cache keys."""
    if not isinstance(table, dict) or "preset" not in table:
        return table
    name = table["preset"]
    known = getattr(registry, "presets", {}).get(axis, {})
    if not isinstance(name, str) or name not in known:
        raise WorkflowError(f"unknown preset {name!r} for axis {axis!r}" + (unknown_key_hint(name, list(known))
                            if isinstance(name, str) else f"; expected one of: {', '.join(sorted(known)) or 'none'}"),
                            source, f"{key}.preset")
    return _merged(known[name], {k: v for k, v in table.items() if k != "preset"})


def _load_value(axis: str, value: str, table: Any, key: str, schema: Optional[type],
                graph: Graph, source: str, base: Path, item_layers: dict, only_raw: dict,
                shares_raw: dict, slot: Optional[str] = None) -> Any:
    check_value_name(value, axis, source)
    table = _table(table, source, key)
    attrs, overrides = {}, {}
    for k, v in table.items():
        if k == "only":  # reserved: where the value takes part (not an attribute, not hashed)
            only_raw[(axis, f"{slot}/{value}" if slot is not None else value)] = v
        elif k == "shares":  # reserved: the value whose identical tasks this one reuses
            shares_raw[(axis, f"{slot}/{value}" if slot is not None else value)] = v
        elif k in graph.stages:
            overrides[k] = P.Layer(_table(v, source, f"{key}.{k}"), source, base,
                                   prefix=f"{key}.{k}")
        else:
            attrs[k] = v
    if overrides:
        item_layers[(axis, f"{slot}/{value}" if slot is not None else value)] = overrides
    if schema is None:
        return attrs
    return P.build(schema, [P.Layer(attrs, source, base, prefix=key)],
                   owner=f"{source}: {key}")
