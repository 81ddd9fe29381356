"""The packages of src/uacell are layers, and imports point down (docs/architecture.md, "Layers").

A module may import its own package, any package of a lower layer, and the few modules every layer
may read, named below with the reason. A new import that points up fails here, naming the import.
Every import counts, as in tests/test_import_cycles.py: ``import uacell.x``, ``from uacell import x``,
``from uacell.x import y``, relative ones, and those inside functions or under ``TYPE_CHECKING``.

The companions are handed to the parts that read them (the composition root asks ``uacell.catalog``,
nothing else does); the declarations a companion makes use types and helpers of the layers below it.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

# top to bottom; packages on one line are one layer and may import each other
LAYERS: tuple[frozenset[str], ...] = (
    frozenset({"entry"}),  # uacell/_entry.py, uacell/__main__.py: the `uacell` command
    frozenset({"cli"}),  # the command line
    frozenset({"root"}),  # the other uacell/*.py: the composition root
    frozenset({"web"}),  # the HMI, an OPC UA client of the server
    frozenset({"security", "services", "history", "pubsub", "sparkplug"}),  # server parts
    frozenset({"machinery"}),  # a companion built on the two below
    frozenset({"gateway"}),  # equipment behind PLCs and controllers
    frozenset({"robotics", "packml", "di"}),  # companions
    frozenset({"binding"}),  # the binder toolkit (and what companions' web views and metrics use)
    frozenset({"ua"}),  # the asyncua adapter
    frozenset({"core", "models"}),  # asyncua-free kernel; where the NodeSets come from
)

# modules any layer may import, and why
EVERYWHERE: dict[str, str] = {
    "uacell": "__version__",
    "uacell.config": "the settings, frozen dataclasses every layer is handed",
    "uacell.host": "Protocols: the read-only views of the server its parts receive",
}

ENTRY = ("_entry", "__main__")


def modules(src: Path = SRC, package: str = "uacell") -> dict[str, Path]:
    """Every module of ``package`` under ``src``, by dotted name (a package by its own name)."""
    found = {}
    for path in (src / package).rglob("*.py"):
        found[".".join(path.relative_to(src).with_suffix("").parts).removesuffix(".__init__")] = path
    return found


def packages(src: Path = SRC, package: str = "uacell") -> set[str]:
    """The sub-packages of ``package`` (directories holding modules, namespace packages too)."""
    return {p.name for p in (src / package).iterdir() if p.is_dir() and any(p.glob("*.py"))}


def package_of(module: str, subpackages: set[str]) -> str:
    """The layer package of ``module``: its sub-package, ``entry`` or ``root``."""
    parts = module.split(".")
    if len(parts) == 2 and parts[1] in ENTRY:
        return "entry"
    if len(parts) > 1 and parts[1] in subpackages:
        return parts[1]
    return "root"


def imported(name: str, path: Path, known: Mapping[str, Path], package: str) -> list[tuple[str, int]]:
    """The modules of ``package`` that module ``name`` imports, anywhere in it: (module, line)."""
    base = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[tuple[str, int]] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                parts = base.split(".")[: len(base.split(".")) - node.level + 1]
                module = ".".join([*parts, module] if module else parts)
            # ``from a import b``: b is a module when a module of that name exists, else a name in a
            targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in known else module for a in node.names]
        else:
            continue
        for target in targets:
            if target.split(".")[0] != package:
                continue
            while target not in known and "." in target:  # ``import uacell.x.y`` names a module of x
                target = target.rpartition(".")[0]
            found.append((target, node.lineno))
    return found


def upward_imports(
    src: Path = SRC,
    package: str = "uacell",
    layers: Sequence[frozenset[str]] = LAYERS,
    everywhere: Mapping[str, str] = EVERYWHERE,
) -> list[str]:
    """Every import of a module of a higher layer, as ``module -> target (line n)``."""
    known = modules(src, package)
    subpackages = packages(src, package)

    def layer(module: str) -> int:
        name = package_of(module, subpackages)
        return next(i for i, members in enumerate(layers) if name in members)

    found = []
    for name, path in sorted(known.items()):
        for target, line in imported(name, path, known, package):
            if target in everywhere or package_of(target, subpackages) == package_of(name, subpackages):
                continue
            if layer(target) < layer(name):
                found.append(f"{name} -> {target} (line {line})")
    return sorted(set(found))


def test_every_package_has_a_layer() -> None:
    named = set().union(*LAYERS)
    assert packages() | {"root", "entry"} == named


def test_the_modules_every_layer_may_read_exist() -> None:
    assert set(EVERYWHERE) <= set(modules())


def test_imports_point_down() -> None:
    found = upward_imports()
    assert found == [], "imports that point up (hand the lower layer what it needs instead):\n" + "\n".join(found)


def test_only_the_composition_root_asks_the_catalog() -> None:
    """``uacell.catalog.companions()`` is no service locator: the entry points, the CLI and the other
    root modules (server, configuration) ask it; every other part receives the companions."""
    known = modules()
    subpackages = packages()
    askers = {
        name
        for name, path in known.items()
        for target, _ in imported(name, path, known, "uacell")
        if target == "uacell.catalog"
    }
    assert askers and {package_of(a, subpackages) for a in askers} <= {"entry", "cli", "root"}, sorted(askers)


def test_the_check_finds_an_injected_upward_import_in_every_form(tmp_path: Path) -> None:
    pkg = tmp_path / "demo"
    for sub in ("core", "core/deep", "web"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("__version__ = '1'\n")
    (pkg / "config.py").write_text("")
    (pkg / "catalog.py").write_text("import demo.web.view\n")  # root -> web: down, allowed
    (pkg / "web" / "view.py").write_text("from demo.core import kernel\nfrom demo import config\n")  # down
    (pkg / "core" / "kernel.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "import demo.web.view\n"  # line 2
        "from demo.web import view\n"  # line 3
        "from demo.web.view import x\n"  # line 4
        "from demo import catalog, config, __version__\n"  # line 5: catalog is up; config, the package are everywhere
        "if TYPE_CHECKING:\n"
        "    from demo.web.view import y\n"  # line 7
        "def f():\n"
        "    from ..web import view\n"  # line 9
    )
    (pkg / "core" / "deep" / "inner.py").write_text("from ...web.view import z\nfrom .. import kernel\n")
    layers = (frozenset({"root"}), frozenset({"web"}), frozenset({"core"}))
    everywhere = {"demo": "version", "demo.config": "settings"}
    assert upward_imports(tmp_path, "demo", layers, everywhere) == [
        "demo.core.deep.inner -> demo.web.view (line 1)",
        "demo.core.kernel -> demo.catalog (line 5)",
        *(f"demo.core.kernel -> demo.web.view (line {n})" for n in (2, 3, 4, 7, 9)),
    ]
    # without the injected imports nothing is found
    (pkg / "core" / "kernel.py").write_text("from demo import config\n")
    (pkg / "core" / "deep" / "inner.py").write_text("from .. import kernel\n")
    assert upward_imports(tmp_path, "demo", layers, everywhere) == []
