"""The engine's modules form a layered order, and the packages' arrows point one way.

Imports are read from the source (every ``import`` / ``from`` statement, including those
inside functions and ``if TYPE_CHECKING:`` blocks), so a cycle that only shows up in type
hints or in a late import is caught too.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("cobgs", "pipeline", "stages", "reports")


def _imports(path: Path, package: str) -> set[str]:
    """Absolute dotted names ``path`` imports (relative imports resolved)."""
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    here = parts if path.name == "__init__.py" else parts[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
                if node.module:
                    out.add(mod)
                else:
                    out.update(f"{mod}.{a.name}" for a in node.names)
            elif node.module:
                out.add(node.module)
    return out


def _module_name(f: Path) -> str:
    parts = list(f.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _module_graph(*packages: str) -> dict[str, set[str]]:
    """module -> the modules (of ``packages``, subpackages included) it imports; an import
    of ``a.b.c`` where ``a.b.c`` is not a module counts as one of ``a.b``."""
    files = {_module_name(f): f for p in packages for f in sorted((REPO / p).rglob("*.py"))}
    graph = {}
    for name, f in files.items():
        deps = set()
        for imp in _imports(f, name.split(".")[0]):
            parts = imp.split(".")
            while parts and ".".join(parts) not in files:
                parts.pop()
            if parts:
                deps.add(".".join(parts))
        # a package's own __init__ is loaded before its modules: an import of the package by
        # one of its modules is no cycle
        graph[name] = {d for d in deps if d != name and not name.startswith(d + ".")}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    state, stack, found = {}, [], []

    def visit(u):
        state[u] = 1
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if v not in graph:
                continue
            if state.get(v) == 1:
                found.append(stack[stack.index(v):] + [v])
            elif not state.get(v):
                visit(v)
        stack.pop()
        state[u] = 2

    for u in sorted(graph):
        if not state.get(u):
            visit(u)
    return found


def test_no_import_cycle_anywhere():
    """No module of cobgs/, pipeline/, stages/ or reports/ reaches itself through imports,
    late imports inside functions included (issue 39: evaluate <-> segment was one)."""
    cycles = _cycles(_module_graph(*PACKAGES))
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c", "a"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_arrows_between_packages_point_one_way():
    """cobgs/ imports none of the others; pipeline/ imports none of cobgs / stages /
    reports; stages/ (stage files) never import reports/ (the layer above them); reports/
    imports only pipeline/ and cobgs/ (the command layer hands it the stage registry and the
    scene reader)."""
    allowed = {"cobgs": set(), "pipeline": set(), "stages": {"cobgs", "pipeline"},
               "reports": {"cobgs", "pipeline"}}
    bad = []
    for package in PACKAGES:
        for f in sorted((REPO / package).rglob("*.py")):
            rel = f.relative_to(REPO)
            if package == "stages" and "commands" in rel.parts:
                continue  # the CLI commands sit above every layer (they hand reports/ the registry)
            for imp in _imports(f, package):
                top = imp.split(".")[0]
                if top in PACKAGES and top != package and top not in allowed[package]:
                    bad.append(f"{rel} imports {imp}")
    assert not bad, "\n".join(bad)


#: The subpackages of cobgs/, lowest first: a module may import modules of its own subpackage
#: and of those listed before it, and the package's top-level modules (configs, errors, ...),
#: which import no subpackage. (ARCHITECTURE.md; issue 47.)
COBGS_LAYERS = ("configs", "gaussians", "render", "data", "evaluate", "masks", "train", "refine")


def _layer_violations() -> list[str]:
    graph = _module_graph("cobgs")
    layer = {name: i for i, name in enumerate(COBGS_LAYERS)}
    bad = []
    for mod, deps in sorted(graph.items()):
        parts = mod.split(".")
        here = parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in layer) else None
        for dep in sorted(deps):
            dp = dep.split(".")
            there = dp[1] if len(dp) > 1 and dp[1] in layer else None
            if there is None or there == here:
                continue
            if here is None:  # a top-level module of cobgs/ (configs, errors, ...) imports a subpackage
                bad.append(f"{mod} (top level) imports {dep}")
            elif layer[there] > layer[here]:
                bad.append(f"{mod} ({here}) imports {dep} ({there}, a layer above)")
    return bad


def test_cobgs_subpackages_form_layers():
    """Inside cobgs/ the subpackages import only those below them (COBGS_LAYERS): render and
    train, train and evaluate, train and data, refine and evaluate no longer import each
    other both ways (the model and its PLY I/O live in gaussians/, SSIM in evaluate/ssim)."""
    bad = _layer_violations()
    assert not bad, "\n".join(bad)
    assert set(COBGS_LAYERS) == {p.name for p in (REPO / "cobgs").iterdir()
                                 if p.is_dir() and (p / "__init__.py").is_file()}


def _private(part: str) -> bool:
    return part.startswith("_") and not (part.startswith("__") and part.endswith("__"))


def private_imports(*packages: str) -> list[str]:
    """Every import of a private name (a module or a name starting with ``_``) from a package
    that is not the importer's own nor one of its ancestors (issue 58: what a subpackage keeps
    private is its own; what a package shares with all its subpackages, such as
    ``cobgs/_atomic.py``, sits in the package itself)."""
    files = {_module_name(f): f for p in packages for f in sorted((REPO / p).rglob("*.py"))}

    def home(mod: str) -> str:
        parts = mod.split(".")
        return mod if files[mod].name == "__init__.py" else ".".join(parts[:-1])

    found = []
    for mod, f in files.items():
        here = home(mod)
        base_parts = mod.split(".") if f.name == "__init__.py" else mod.split(".")[:-1]
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(base_parts[: len(base_parts) - node.level + 1] + ([node.module] if node.module else []))
                names = [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for full in names:
                parts = full.split(".")
                k = len(parts)
                while k and ".".join(parts[:k]) not in files:
                    k -= 1
                if not k or parts[0] not in packages:
                    continue
                owner = home(".".join(parts[:k]))
                if here == owner or here.startswith(owner + "."):
                    continue  # its own package, or an ancestor's shared helpers
                if any(_private(p) for p in parts[len(owner.split(".")):]):
                    found.append(f"{f.relative_to(REPO)}:{node.lineno} imports {full}")
    return found


def test_no_private_name_is_imported_from_another_subpackage():
    """Issue 58 item 7: train/losses.py took evaluate.ssim's _check_pair / _gauss_1d,
    stages/sfm.py data.sfm's _check_camera, the commands render._build; what another
    subpackage needs is public in its module."""
    assert private_imports(*PACKAGES) == []


def test_the_private_import_finder_finds_one(tmp_path, monkeypatch):
    import sys

    pkg = tmp_path / "pkg"
    for sub in ("a", "b"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "_shared.py").write_text("def _h(): pass\n")
    (pkg / "a" / "m.py").write_text("def _x(): pass\n")
    (pkg / "b" / "n.py").write_text("from pkg.a.m import _x\nfrom pkg._shared import _h\nfrom ..a import m\n")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert private_imports("pkg") == ["pkg/b/n.py:1 imports pkg.a.m._x"]
