"""The package layout is the architecture: no import cycles, each subpackage imports only
the layers its ``__init__`` declares, no module at the package root but the face and the
entry point, the evidence (``prove``) apart from the method (``discovery``: it never imports
``prove``; only the CLI does), and the CLI stays thin."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "twin_nodes"
ROOTS = ("twin_nodes", "msgs_py")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def runtime_imports(path: Path) -> set[str]:
    """Every module named by an import that runs (anywhere in the file, lazy imports
    included), skipping ``if TYPE_CHECKING:`` blocks."""
    found: set[str] = set()

    class Visitor(ast.NodeVisitor):
        def visit_If(self, node: ast.If) -> None:
            if _is_type_checking(node.test):
                for n in node.orelse:
                    self.visit(n)
                return
            self.generic_visit(node)

        def visit_Import(self, node: ast.Import) -> None:
            found.update(a.name for a in node.names)

        def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
            if node.level == 0 and node.module:
                found.add(node.module)
                found.update(f"{node.module}.{a.name}" for a in node.names)

    Visitor().visit(ast.parse(path.read_text(encoding="utf-8")))
    return found


@functools.lru_cache(maxsize=1)
def module_graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for r in ROOTS for p in (ROOT / r).rglob("*.py")}
    graph = {}
    for name, path in files.items():
        deps = set()
        for imp in runtime_imports(path):
            # ``from pkg import mod`` names a module; ``from mod import func`` names mod
            while imp and imp not in files:
                imp = imp.rpartition(".")[0]
            if imp and imp != name:
                deps.add(imp)
        graph[name] = deps
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a list of modules, or None (iterative DFS, colour marking).

    A package's ``__init__`` importing its own submodules is not a cycle worth failing on
    (Python resolves it), so edges from a package to its children are ignored."""
    def edges(m: str) -> list[str]:
        return sorted(d for d in graph[m] if not d.startswith(m + "."))
    colour = dict.fromkeys(graph, 0)
    for start in sorted(graph):
        if colour[start]:
            continue
        stack = [(start, iter(edges(start)))]
        path = [start]
        colour[start] = 1
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                colour[node] = 2
                stack.pop()
                path.pop()
            elif colour[nxt] == 1:
                return path[path.index(nxt):] + [nxt]
            elif colour[nxt] == 0:
                colour[nxt] = 1
                stack.append((nxt, iter(edges(nxt))))
                path.append(nxt)
    return None


def layer(module: str) -> str:
    parts = module.split(".")
    if parts[0] != "twin_nodes":
        return parts[0]
    return parts[1] if len(parts) > 1 else "twin_nodes"


def declared_imports(subpackage: Path) -> set[str] | None:
    doc = ast.get_docstring(ast.parse((subpackage / "__init__.py").read_text(encoding="utf-8"))) or ""
    m = re.search(r"^May import: (.*)$", doc, re.M)
    if m is None:
        return None
    text = re.sub(r"\(.*?\)", "", m.group(1)).strip().rstrip(".")
    if text.startswith("nothing") or text == "anything":
        return set() if text.startswith("nothing") else None
    return {w.strip() for w in text.split(",") if w.strip()}


SUBPACKAGES = sorted(p for p in PKG.iterdir() if (p / "__init__.py").exists())


def test_no_import_cycle():
    assert find_cycle(module_graph()) is None, f"import cycle: {' -> '.join(find_cycle(module_graph()))}"


def test_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


@pytest.mark.parametrize("sub", [p.name for p in SUBPACKAGES if p.name != "cli"])
def test_subpackage_imports_only_declared_layers(sub):
    allowed = declared_imports(PKG / sub)
    assert allowed is not None, f"twin_nodes/{sub}/__init__.py must say 'May import: ...' in its docstring"
    graph = module_graph()
    bad = sorted(f"{m} -> {d}" for m, deps in graph.items() if layer(m) == sub
                 for d in deps if layer(d) not in allowed | {sub})
    assert not bad, f"{sub} may import {sorted(allowed)} only: " + "; ".join(bad)


def test_declared_layers_are_acyclic():
    decl = {p.name: declared_imports(p) or set() for p in SUBPACKAGES if p.name != "cli"}
    graph = {k: {d for d in v if d in decl} for k, v in decl.items()}
    assert find_cycle(graph) is None


def test_package_root_holds_only_face_and_entry_point():
    assert sorted(p.name for p in PKG.glob("*.py")) == ["__init__.py", "__main__.py"]


def test_cli_modules_are_thin():
    long = {p.name: n for p in (PKG / "cli").glob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 250}
    assert not long, f"CLI modules over 250 lines (move the logic below the CLI): {long}"


#: the evidence package: it imports the method, and only the CLI imports it
EVIDENCE = "prove"
#: the layers that may import the evidence package (besides itself)
EVIDENCE_USERS = {"cli"}


def evidence_importers(graph: dict[str, set[str]]) -> list[str]:
    """``module -> prove module`` for every import of the evidence package from outside it and the CLI."""
    return sorted(f"{m} -> {d}" for m, deps in graph.items() for d in deps
                  if layer(d) == EVIDENCE and layer(m) not in EVIDENCE_USERS | {EVIDENCE})


def test_prove_is_a_declared_subpackage_above_discovery():
    assert (PKG / EVIDENCE / "__init__.py").exists()
    allowed = declared_imports(PKG / EVIDENCE)
    assert allowed is not None and "discovery" in allowed
    assert EVIDENCE not in (declared_imports(PKG / "discovery") or set())


def test_nothing_but_the_cli_imports_prove():
    """discovery (the method) must not depend on its evidence; no other layer does either."""
    bad = evidence_importers(module_graph())
    assert not bad, "only the CLI may import twin_nodes.prove: " + "; ".join(bad)


def test_evidence_rule_catches_discovery_importing_prove():
    graph = {"twin_nodes.discovery.plan_flight": {"twin_nodes.prove.ours"},
             "twin_nodes.cli.discover": {"twin_nodes.prove.sources"},
             "twin_nodes.prove.ours": {"twin_nodes.discovery.discover"}}
    assert evidence_importers(graph) == ["twin_nodes.discovery.plan_flight -> twin_nodes.prove.ours"]


def test_msgs_py_depends_on_nothing_of_ours():
    graph = module_graph()
    assert not {d for m, deps in graph.items() if m.startswith("msgs_py") for d in deps
                if d.startswith("twin_nodes")}


#: discovery is read stage by stage (``twin_nodes/discovery/stages/``, docs/ARCHITECTURE.md "Discovery
#: stages"): no function in it over this many lines, no module over MAX_MODULE_LINES
MAX_FUNCTION_LINES = 80
MAX_MODULE_LINES = 600
DISCOVERY = PKG / "discovery"


def long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> dict[str, int]:
    """``name: lines`` of every function (nested ones and methods included) longer than ``limit``
    lines, counted by ``ast`` (end_lineno - lineno + 1)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {f"{path.name}:{n.name}": n.end_lineno - n.lineno + 1 for n in ast.walk(tree)
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.end_lineno - n.lineno + 1 > limit}


def test_discovery_functions_are_short():
    long = {k: v for p in sorted(DISCOVERY.rglob("*.py")) for k, v in long_functions(p).items()}
    assert not long, f"discovery functions over {MAX_FUNCTION_LINES} lines (split them): {long}"


def test_discovery_modules_are_small():
    big = {str(p.relative_to(DISCOVERY)): n for p in sorted(DISCOVERY.rglob("*.py"))
           if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not big, f"discovery modules over {MAX_MODULE_LINES} lines (split them): {big}"


def test_length_rule_catches_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    p = tmp_path / "m.py"
    p.write_text(f"def short():\n    return 1\n\n\ndef long():\n{body}\n    return 0\n", encoding="utf-8")
    assert long_functions(p) == {"m.py:long": MAX_FUNCTION_LINES + 2}


def _gravity_literals(source: str) -> list[int]:
    """Lines where standard gravity is written as a number in code (docstrings and comments aside)."""
    tree = ast.parse(source)
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
            and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and id(n) not in docs
            and isinstance(n.value, float) and abs(n.value - 9.80665) < 1e-9]


def test_standard_gravity_has_one_home():
    """Standard gravity is written once (``base/constants.py``); every other module imports it, so the twin,
    its identification and its checks cannot drift apart. (RotorPy's 9.81 is RotorPy's own constant.)"""
    found = {str(p.relative_to(ROOT)): lines for p in sorted(PKG.rglob("*.py"))
             if (lines := _gravity_literals(p.read_text(encoding="utf-8")))}
    home = (PKG / "base" / "constants.py").read_text(encoding="utf-8").splitlines()
    assert found == {"twin_nodes/base/constants.py": [home.index("G_STANDARD_M_S2 = 9.80665") + 1]}


def test_gravity_rule_sees_a_literal_and_not_a_docstring():
    assert _gravity_literals('"""g = 9.80665"""\nG = 9.80665\n') == [2]
    assert _gravity_literals('def f(g=9.80665):\n    """9.80665"""\n') == [1]
