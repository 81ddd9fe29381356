"""Finds where a module touches asyncua (or uvicorn) past its public surface: a private name reached
from an asyncua module, class or object, an attribute of one assigned or deleted, ``setattr`` on one,
or a subclass of one that the door does not register. Used by tests/test_asyncua_door.py on every
module of ``uacell`` outside ``uacell.ua.door``.

What counts as an asyncua object, statically:
- a name imported from ``asyncua``/``uvicorn`` (module or class), and what is reached from it;
- a parameter or variable annotated with such a class (``asyncua.ua``'s data types excepted: they are
  values, free to fill), and a variable assigned from an asyncua object;
- what the names by which uacell reaches asyncua's server parts lead to (``iserver``, ``aspace``,
  ``isession``, the services), and ``self.X`` where a method of the class set it from an asyncua object;
- in a class whose base is an asyncua class: ``self``'s attributes that the base defines, and
  anything reached through ``super()``.
A uacell private (``self._locks`` in a uacell class, ``_helper()``) is none of these."""

from __future__ import annotations

import ast
import importlib
import inspect
import re
from dataclasses import dataclass

ROOTS = ("asyncua", "uvicorn")
DATA_MODULES = ("asyncua.ua",)  # value types: their instances are filled freely
# Attributes by which uacell reaches asyncua's objects from its own.
BRIDGES = frozenset(
    {
        "iserver",
        "aspace",
        "isession",
        "subscription_service",
        "view_service",
        "node_mgt_service",
        "attribute_service",
        "method_service",
        "history_manager",
    }
)
# Attributes that lead to values asyncua hands out to be filled (an event's fields).
VALUES = frozenset({"event"})
DOOR_DECORATOR = "subclass"  # ``@door.subclass(KEY)``


@dataclass(frozen=True)
class Touch:
    module: str
    line: int
    what: str

    def __str__(self) -> str:
        return f"{self.module}:{self.line}: {self.what}"


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _foreign(module: str) -> bool:
    return module.split(".")[0] in ROOTS


def _data(module: str) -> bool:
    return any(module == m or module.startswith(m + ".") for m in DATA_MODULES)


def _base_privates(module: str, name: str) -> frozenset[str]:
    """The private names an asyncua class (and its bases) defines: methods, class attributes and what
    its ``__init__`` sets on ``self``."""
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return frozenset()
    found: set[str] = set()
    for klass in inspect.getmro(cls):
        if klass is object:
            continue
        found.update(n for n in vars(klass) if _is_private(n))
        try:
            source = inspect.getsource(klass)
        except (OSError, TypeError):
            continue
        found.update(re.findall(r"self\.(_[A-Za-z]\w*)\s*[:=]", source))
    return frozenset(n for n in found if _is_private(n))


class _Checker(ast.NodeVisitor):
    def __init__(self, module: str) -> None:
        self.module = module
        self.touches: list[Touch] = []
        self.names: dict[str, str] = {}  # local name -> asyncua module path it was imported from
        self.data_names: set[str] = set()
        self.scopes: list[dict[str, str]] = [{}]  # names bound to asyncua objects (-> package), per function
        self.classes: list[frozenset[str] | None] = []  # base privates of the enclosing asyncua subclass
        self.self_attrs: list[set[str]] = [set()]  # attributes of self set from asyncua objects, per class

    def flag(self, node: ast.AST, what: str) -> None:
        self.touches.append(Touch(self.module, getattr(node, "lineno", 0), what))

    # --- imports -------------------------------------------------------------------------------
    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            if _foreign(alias.name):
                if any(_is_private(part) for part in alias.name.split(".")):
                    self.flag(node, f"imports asyncua's private module {alias.name}")
                local = alias.asname or alias.name.split(".")[0]
                self.names[local] = alias.name if alias.asname else alias.name.split(".")[0]

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        module = node.module or ""
        if not _foreign(module):
            return
        if any(_is_private(part) for part in module.split(".")):
            self.flag(node, f"imports from asyncua's private module {module}")
        for alias in node.names:
            if _is_private(alias.name):
                self.flag(node, f"imports asyncua's private name {module}.{alias.name}")
            local = alias.asname or alias.name
            self.names[local] = f"{module}.{alias.name}"
            if _data(f"{module}.{alias.name}"):
                self.data_names.add(local)

    # --- what is an asyncua object ---------------------------------------------------------------
    def _annotated(self, annotation: ast.expr | None) -> bool:
        if annotation is None:
            return False
        if isinstance(annotation, ast.Constant) and isinstance(annotation.value, str):
            try:
                annotation = ast.parse(annotation.value, mode="eval").body
            except SyntaxError:
                return False
        for sub in ast.walk(annotation):
            if isinstance(sub, ast.Name) and sub.id in self.names and sub.id not in self.data_names:
                return True
        return False

    def _annotation_root(self, annotation: ast.expr | None) -> str:
        for sub in ast.walk(annotation) if annotation is not None else ():
            if isinstance(sub, ast.Name) and sub.id in self.names:
                return self.names[sub.id].split(".")[0]
        return "asyncua"

    def foreign(self, node: ast.expr) -> bool:
        """Whether ``node`` evaluates to an asyncua module, class or (non-value) object."""
        if isinstance(node, ast.Name):
            return node.id in self.names or node.id in BRIDGES or node.id in self.scopes[-1]
        if isinstance(node, ast.Attribute):
            if node.attr in VALUES:
                return False
            if isinstance(node.value, ast.Name) and node.value.id == "self" and node.attr in self.self_attrs[-1]:
                return True
            return node.attr in BRIDGES or self.foreign(node.value)
        if isinstance(node, ast.Subscript):
            return self.foreign(node.value)
        if isinstance(node, ast.Call):
            func = node.func
            if isinstance(func, ast.Name):  # an asyncua class instantiated
                return func.id in self.names and func.id not in self.data_names
            if isinstance(func, ast.Attribute) and self.foreign(func.value):
                return not self._data_rooted(func.value)
            return False
        return False

    def _made(self, node: ast.expr) -> bool:
        """An asyncua class instantiated by uacell (a Client, a NodeData): its own object to configure."""
        return isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in self.names

    def _root(self, node: ast.expr) -> str:
        """The package an expression's name was imported from ("" when it is no imported name)."""
        while isinstance(node, (ast.Attribute, ast.Subscript, ast.Call)):
            node = node.func if isinstance(node, ast.Call) else node.value
        if isinstance(node, ast.Name):
            if node.id in self.names:
                return self.names[node.id].split(".")[0]
            return self.scopes[-1].get(node.id, "")
        return ""

    def _data_rooted(self, node: ast.expr) -> bool:
        while isinstance(node, (ast.Attribute, ast.Subscript, ast.Call)):
            node = node.func if isinstance(node, ast.Call) else node.value
        return isinstance(node, ast.Name) and node.id in self.data_names

    def _instance(self, node: ast.expr) -> bool:
        """An asyncua object whose attributes may not be assigned (a value type's instance may)."""
        return self.foreign(node)

    # --- scopes --------------------------------------------------------------------------------
    def _function(self, node: ast.FunctionDef | ast.AsyncFunctionDef) -> None:
        bound: dict[str, str] = {}
        args = node.args
        for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg]:
            if arg is not None and self._annotated(arg.annotation):
                bound[arg.arg] = self._annotation_root(arg.annotation)
        self.scopes.append(bound)
        for decorator in node.decorator_list:
            self.visit(decorator)
        self.visit(args)
        for statement in node.body:
            self.visit(statement)
        self.scopes.pop()

    visit_FunctionDef = _function
    visit_AsyncFunctionDef = _function

    def visit_ClassDef(self, node: ast.ClassDef) -> None:
        privates: set[str] = set()
        foreign_base = False
        for base in node.bases:
            target = base
            while isinstance(target, ast.Attribute):
                target = target.value
            if isinstance(target, ast.Name) and target.id in self.names:
                foreign_base = True
                path = self.names[target.id]
                if isinstance(base, ast.Name):
                    module, _, name = path.rpartition(".")
                else:
                    module, name = path, ast.unparse(base).split(".", 1)[1]
                    module, _, name = f"{module}.{name}".rpartition(".")
                privates |= _base_privates(module, name)
        if foreign_base and not any(_registers(d) for d in node.decorator_list):
            self.flag(
                node, f"class {node.name} subclasses asyncua's {ast.unparse(node.bases[0])} without @door.subclass"
            )
        self.classes.append(frozenset(privates) if foreign_base else None)
        self.self_attrs.append(_self_attributes(node, self))
        self.generic_visit(node)
        self.self_attrs.pop()
        self.classes.pop()

    # --- touches -------------------------------------------------------------------------------
    def _self_private(self, node: ast.Attribute) -> bool:
        """``self.X`` (or ``super().X``) in an asyncua subclass, X a private of the base."""
        privates = self.classes[-1] if self.classes else None
        if privates is None or not _is_private(node.attr):
            return False
        value = node.value
        if isinstance(value, ast.Call) and isinstance(value.func, ast.Name) and value.func.id == "super":
            return True
        return isinstance(value, ast.Name) and value.id == "self" and node.attr in privates

    def visit_Attribute(self, node: ast.Attribute) -> None:
        if _is_private(node.attr) and (self.foreign(node.value) or self._self_private(node)):
            self.flag(node, f"reaches asyncua's private {ast.unparse(node)}")
        self.generic_visit(node)

    def _target(self, target: ast.expr, verb: str) -> None:
        if (
            isinstance(target, ast.Attribute)
            and self._instance(target.value)
            and self._root(target.value) not in ("uvicorn", "made")
        ):
            self.flag(target, f"{verb} {ast.unparse(target)} on an asyncua object")
        elif isinstance(target, (ast.Tuple, ast.List)):
            for element in target.elts:
                self._target(element, verb)

    def _bind(self, target: ast.expr, value: ast.expr | None, annotation: ast.expr | None = None) -> None:
        if isinstance(target, ast.Name):
            scope = self.scopes[-1]
            if self._annotated(annotation):
                scope[target.id] = self._annotation_root(annotation)
            elif value is not None and self._made(value):
                scope[target.id] = "made"
            elif value is not None and self.foreign(value) and not self._data_rooted(value):
                scope[target.id] = self._root(value) or "asyncua"
            else:
                scope.pop(target.id, None)

    def visit_Assign(self, node: ast.Assign) -> None:
        self.visit(node.value)
        for target in node.targets:
            self._target(target, "assigns")
            self._bind(target, node.value)
            self.visit(target)

    def visit_AnnAssign(self, node: ast.AnnAssign) -> None:
        if node.value is not None:
            self.visit(node.value)
        self._target(node.target, "assigns")
        self._bind(node.target, node.value, node.annotation)
        self.visit(node.target)

    def visit_AugAssign(self, node: ast.AugAssign) -> None:
        self._target(node.target, "assigns")
        self.generic_visit(node)

    def visit_Delete(self, node: ast.Delete) -> None:
        for target in node.targets:
            self._target(target, "deletes")
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        func = node.func
        if isinstance(func, ast.Name) and func.id in ("setattr", "delattr", "getattr") and node.args:
            name = node.args[1] if len(node.args) > 1 else None
            private = isinstance(name, ast.Constant) and isinstance(name.value, str) and _is_private(name.value)
            if self.foreign(node.args[0]) and (func.id != "getattr" or private):
                self.flag(node, f"{func.id} on an asyncua object: {ast.unparse(node)}")
        self.generic_visit(node)


def _self_attributes(node: ast.ClassDef, checker: _Checker) -> set[str]:
    """Attributes a class's methods set on ``self`` from an asyncua object (a parameter annotated with
    an asyncua class, or a value reached from one)."""
    found: set[str] = set()
    for method in node.body:
        if not isinstance(method, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        args = method.args
        params = {
            a.arg: "asyncua"
            for a in [*args.posonlyargs, *args.args, *args.kwonlyargs]
            if checker._annotated(a.annotation)
        }
        checker.scopes.append(params)
        for sub in ast.walk(method):
            targets: list[ast.expr] = []
            value: ast.expr | None = None
            annotation: ast.expr | None = None
            if isinstance(sub, ast.Assign):
                targets, value = sub.targets, sub.value
            elif isinstance(sub, ast.AnnAssign):
                targets, value, annotation = [sub.target], sub.value, sub.annotation
            for target in targets:
                if (
                    isinstance(target, ast.Attribute)
                    and isinstance(target.value, ast.Name)
                    and target.value.id == "self"
                    and (
                        checker._annotated(annotation)
                        or (
                            value is not None
                            and checker.foreign(value)
                            and not checker._data_rooted(value)
                            and not checker._made(value)
                        )
                    )
                ):
                    found.add(target.attr)
        checker.scopes.pop()
    return found


def _registers(decorator: ast.expr) -> bool:
    """``@door.subclass(...)`` (or ``@subclass(...)`` imported from the door)."""
    call = decorator.func if isinstance(decorator, ast.Call) else decorator
    name = call.attr if isinstance(call, ast.Attribute) else call.id if isinstance(call, ast.Name) else ""
    return name == DOOR_DECORATOR


def touches(source: str, module: str) -> list[Touch]:
    checker = _Checker(module)
    checker.visit(ast.parse(source))
    return checker.touches
