"""No import cycles among uacell's modules (docs/architecture.md, "Which way imports go").

Every import counts: top-level, function-level and those under ``TYPE_CHECKING``. A cycle means two
modules cannot be understood, tested or replaced apart; the fix is a narrower dependency (a Protocol
in a leaf module, a parameter, a name looked up at the composition root), never a local import.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

SRC = Path(__file__).resolve().parent.parent / "src"
PACKAGE = "uacell"


def module_graph(src: Path = SRC, package: str = PACKAGE) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (a package's own ``__init__`` and parents excluded)."""
    files = {}
    for f in (src / package).rglob("*.py"):
        files[".".join(f.relative_to(src).with_suffix("").parts).removesuffix(".__init__")] = f

    def resolve(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in files}
    for module, f in files.items():
        base = module if f.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                name = node.module or ""
                if node.level:
                    parts = base.split(".")[: len(base.split(".")) - node.level + 1]
                    name = ".".join([*parts, name] if name else parts)
                targets = [f"{name}.{a.name}" for a in node.names] + [name]
            else:
                continue
            for target in targets:
                found = resolve(target) if target.startswith(package) else None
                if found and found not in (module, package) and not module.startswith(found + "."):
                    graph[module].add(found)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == v:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def test_uacell_has_no_import_cycles() -> None:
    found = cycles(module_graph())
    assert found == [], "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_the_benchmarks_have_no_import_cycles() -> None:
    """The sections import ``benchmarks.harness``, never ``benchmarks.__main__`` (which imports them)."""
    graph = module_graph(SRC.parent, "benchmarks")
    assert "benchmarks.harness" in graph and graph["benchmarks.__main__"]  # the walk found the package
    found = cycles(graph)
    assert found == [], "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_the_walk_counts_function_level_and_type_checking_imports(tmp_path: Path) -> None:
    pkg = tmp_path / "demo"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from demo.b import B\n")
    (pkg / "b.py").write_text("def f():\n    from .sub import c\n")
    (pkg / "sub" / "c.py").write_text("from ..a import x\n")
    (pkg / "d.py").write_text("import demo.a\n")
    graph = module_graph(tmp_path, "demo")
    assert (
        graph["demo.a"] == {"demo.b"}
        and graph["demo.b"] == {"demo.sub", "demo.sub.c"}
        and graph["demo.sub.c"] == {"demo.a"}
    )
    assert cycles(graph) == [["demo.a", "demo.b", "demo.sub.c"]]


# asyncua's objects uacell holds, by the names the code gives them; their underscored attributes are
# asyncua's private state, read only by the adapter (uacell.ua, mostly uacell.ua.channel).
_ASYNCUA_OBJECTS = r"\b(iserver|aspace|processor|isession|transport|protocol|uaprocessor|bserver)\._[A-Za-z]\w*"


def test_no_module_outside_the_asyncua_adapter_touches_asyncua_private_attributes() -> None:
    src = Path(__file__).resolve().parents[1] / "src" / "uacell"
    found = []
    for path in sorted(src.rglob("*.py")):
        if path.relative_to(src).parts[0] == "ua":
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(_ASYNCUA_OBJECTS, line.split("#", 1)[0]):
                found.append(f"{path.relative_to(src)}:{number}: {line.strip()}")
    assert found == [], "use (or add) a function in uacell.ua.channel instead:\n" + "\n".join(found)
