"""State-machine tables read from the official NodeSet files.

The NodeSets already hold every state machine's rules: its State and Transition objects with their
StateNumber/TransitionNumber, FromState, ToState and HasCause references. uacell reads them from
there (never types them twice); the pure models and the OPC UA binding both use these tables.

Identifiers are kept as ``NodeRef`` (namespace URI, numeric id) so that they mean the same thing
whatever namespace index a server gives the model.
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from uacell.models.model_file import ModelFile
from uacell.models.source import locate_models, model_by_key

UA_NS = "http://opcfoundation.org/UA/"
_X = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"
_STATE_TYPES = {(UA_NS, 2307), (UA_NS, 2309)}  # StateType, InitialStateType
_INITIAL_STATE_TYPE = (UA_NS, 2309)
_TRANSITION_TYPE = (UA_NS, 2310)
# Well-known ns0 reference types by id.
_REF_IDS = {
    "HasComponent": 47,
    "HasProperty": 46,
    "HasTypeDefinition": 40,
    "HasSubtype": 45,
    "FromState": 51,
    "ToState": 52,
    "HasCause": 53,
    "HasEffect": 54,
    "HasSubStateMachine": 117,
}

NodeRef = tuple[str, int]


@dataclass(frozen=True)
class StateInfo:
    name: str
    node: NodeRef
    number: int
    initial: bool
    submachine: str | None  # BrowseName (name part) of the sub-state machine entered with this state


@dataclass(frozen=True)
class TransitionInfo:
    name: str
    node: NodeRef
    number: int | None  # None where the NodeSet gives no TransitionNumber value
    from_state: str
    to_state: str
    causes: tuple[str, ...]  # BrowseNames (name part) of the methods that cause it


@dataclass(frozen=True)
class FsmTable:
    """The states and transitions of one FiniteStateMachineType, as the NodeSet declares them."""

    type_name: str
    type_node: NodeRef
    states: dict[str, StateInfo]
    transitions: dict[str, TransitionInfo]
    _by_cause: dict[tuple[str, str], TransitionInfo] = field(default_factory=dict, repr=False)
    _methods: frozenset[str] = field(default=frozenset(), repr=False)
    _numbers: dict[str, int] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        for t in self.transitions.values():
            for method in t.causes:
                self._by_cause.setdefault((method, t.from_state), t)
        # Asked on every Executable evaluation: made once (the table does not change).
        object.__setattr__(self, "_methods", frozenset(m for t in self.transitions.values() for m in t.causes))
        # uacell's numbering where the type gives none (``transition_number``), made once
        ordered = sorted(self.transitions.values(), key=lambda x: x.node[1])
        for position, t in enumerate(ordered, start=1):
            self._numbers[t.name] = t.number if t.number is not None else position

    def caused_by(self, method: str, from_state: str) -> TransitionInfo | None:
        """The transition ``method`` causes from ``from_state``, if there is one."""
        return self._by_cause.get((method, from_state))

    def between(self, from_state: str, to_state: str) -> TransitionInfo:
        for t in self.transitions.values():
            if t.from_state == from_state and t.to_state == to_state:
                return t
        raise KeyError(f"{self.type_name} has no transition {from_state} -> {to_state}")

    @property
    def methods(self) -> frozenset[str]:
        """The methods that cause a transition of this type (its HasCause references)."""
        return self._methods

    def check_names(self, states: Iterable[str] = (), methods: Iterable[str] = ()) -> None:
        """Raise ``LookupError`` unless the type declares every state and method named in code."""
        missing = [s for s in states if s not in self.states] + [m for m in methods if m not in self.methods]
        if missing:
            raise LookupError(f"{self.type_name} in the NodeSet has no {', '.join(missing)}")

    def transition_number(self, name: str) -> int:
        """The TransitionNumber from the type, or uacell's numbering where the type gives none.

        uacell's numbering: the transitions of the type in ascending NodeId order, counted from 1.
        """
        if name not in self.transitions:
            raise KeyError(name)
        return self._numbers[name]


@dataclass
class _Node:
    ref: NodeRef
    node_class: str
    browse_name: str
    refs: list[tuple[int, NodeRef, bool]]  # (ns0 reference type id or -1, target, is_forward)
    value: ET.Element | None


class NodeSetIndex:
    """A read-only index of one NodeSet2 file's nodes and references (both directions)."""

    def __init__(self, path: Path) -> None:
        root = ET.parse(path).getroot()
        uris = [UA_NS] + [u.text or "" for u in root.iter(_X + "Uri")]
        aliases = {a.get("Alias"): (a.text or "").strip() for a in root.iter(_X + "Alias")}
        self.nodes: dict[NodeRef, _Node] = {}

        def ref_of(text: str) -> NodeRef:
            text = aliases.get(text, text).strip()
            ns = 0
            if text.startswith("ns="):
                head, text = text.split(";", 1)
                ns = int(head[3:])
            if not text.startswith("i="):
                return (uris[ns], -1)
            return (uris[ns], int(text[2:]))

        for element in root:
            tag = element.tag.removeprefix(_X)
            if not tag.startswith("UA") or element.get("NodeId") is None:
                continue
            me = ref_of(element.get("NodeId", ""))
            name = element.get("BrowseName", "")
            self.nodes[me] = _Node(me, tag, name.split(":", 1)[-1], [], element.find(_X + "Value"))
        for element in root:
            if element.get("NodeId") is None:
                continue
            me = ref_of(element.get("NodeId", ""))
            refs = element.find(_X + "References")
            for r in refs if refs is not None else []:
                rtype = ref_of(r.get("ReferenceType", ""))
                rid = rtype[1] if rtype[0] == UA_NS else -1
                target = ref_of(r.text or "")
                forward = r.get("IsForward", "true").lower() != "false"
                self.nodes[me].refs.append((rid, target, forward))
                if target in self.nodes:
                    self.nodes[target].refs.append((rid, me, not forward))

    def targets(self, node: NodeRef, ref_name: str, forward: bool = True) -> list[NodeRef]:
        rid = _REF_IDS[ref_name]
        seen: list[NodeRef] = []
        for r, target, fwd in self.nodes[node].refs:
            if r == rid and fwd == forward and target not in seen:
                seen.append(target)
        return seen

    def find_type(self, name: str) -> NodeRef:
        for node in self.nodes.values():
            if node.node_class == "UAObjectType" and node.browse_name == name:
                return node.ref
        raise KeyError(f"no ObjectType {name!r}")

    def child(self, node: NodeRef, name: str) -> NodeRef | None:
        for target in self.targets(node, "HasProperty") + self.targets(node, "HasComponent"):
            if target in self.nodes and self.nodes[target].browse_name == name:
                return target
        return None

    def number_value(self, node: NodeRef, prop: str) -> int | None:
        child = self.child(node, prop)
        if child is None:
            return None
        value = self.nodes[child].value
        if value is None or len(value) == 0 or value[0].text is None:
            return None
        return int(value[0].text)


@functools.cache
def _index(model_key: str, path: Path) -> NodeSetIndex:
    return NodeSetIndex(path)


def index_for(models: Iterable[ModelFile], model_key: str, models_dir: str | None = None) -> NodeSetIndex:
    path = locate_models(models, models_dir)[model_key]
    return _index(model_key, path)


def table_from_index(index: NodeSetIndex, type_name: str) -> FsmTable:
    type_node = index.find_type(type_name)
    holder = type_node
    # A subtype without State objects of its own uses its supertype's.
    while True:
        members = index.targets(holder, "HasComponent")
        typed = {m: index.targets(m, "HasTypeDefinition") for m in members if m in index.nodes}
        if any(t and t[0] in _STATE_TYPES for t in typed.values()):
            break
        supers = index.targets(holder, "HasSubtype", forward=False)
        if not supers or supers[0] not in index.nodes:
            break
        holder = supers[0]
    states: dict[str, StateInfo] = {}
    transitions: dict[str, TransitionInfo] = {}
    names = {m: index.nodes[m].browse_name for m in typed}
    for member, tdef in typed.items():
        if not tdef or (tdef[0] not in _STATE_TYPES):
            continue
        sub = index.targets(member, "HasSubStateMachine")
        states[names[member]] = StateInfo(
            name=names[member],
            node=member,
            number=index.number_value(member, "StateNumber") or 0,
            initial=tdef[0] == _INITIAL_STATE_TYPE,
            submachine=index.nodes[sub[0]].browse_name if sub and sub[0] in index.nodes else None,
        )
    for member, tdef in typed.items():
        if not tdef or tdef[0] != _TRANSITION_TYPE:
            continue
        src = index.targets(member, "FromState")[0]
        dst = index.targets(member, "ToState")[0]
        causes = tuple(index.nodes[c].browse_name for c in index.targets(member, "HasCause") if c in index.nodes)
        transitions[names[member]] = TransitionInfo(
            name=names[member],
            node=member,
            number=index.number_value(member, "TransitionNumber"),
            from_state=index.nodes[src].browse_name,
            to_state=index.nodes[dst].browse_name,
            causes=causes,
        )
    return FsmTable(type_name, type_node, states, transitions)


@functools.cache
def _cached_table(models: tuple[ModelFile, ...], model_key: str, type_name: str, models_dir: str | None) -> FsmTable:
    return table_from_index(index_for(models, model_key, models_dir), type_name)


def fsm_table(models: Iterable[ModelFile], model_key: str, type_name: str, models_dir: str | None = None) -> FsmTable:
    """The table of ``type_name`` (e.g. ``"TaskControlStateMachineType"``) from model ``model_key``,
    one of the official ``models`` (``uacell.models.source.official_models``)."""
    models = tuple(models)
    if model_by_key(models, model_key) is None:
        raise KeyError(f"unknown model {model_key!r}")
    return _cached_table(models, model_key, type_name, models_dir)


# What the models are handed: (model key, type BrowseName) -> that type's table.
TableLoader = Callable[[str, str], FsmTable]


class StateTables:
    """The ``TableLoader`` over the official ``models`` in one models directory (each table read once).

    The server builds it from its companions' models and ``[server] models_dir``; pure models receive
    the tables it returns and never read a file themselves.
    """

    def __init__(self, models: Iterable[ModelFile], models_dir: str | None = None) -> None:
        self.models = tuple(models)
        self.models_dir = models_dir
        self._made: dict[tuple[str, str], FsmTable] = {}

    def __call__(self, model_key: str, type_name: str) -> FsmTable:
        table = self._made.get((model_key, type_name))
        if table is None:
            table = self._made[(model_key, type_name)] = fsm_table(self.models, model_key, type_name, self.models_dir)
        return table

    def made(self) -> dict[tuple[str, str], FsmTable]:
        """Every table asked for so far, by (model key, type name)."""
        return dict(self._made)

    def adopt(self, tables: object) -> int:
        """Take tables made before from the same NodeSet files (``made`` of an earlier server, kept in
        the address-space snapshot, which is keyed by the files' digests): asked for, they are not
        read from the files again. Anything else than such a mapping is ignored; how many were taken."""
        if not isinstance(tables, dict):
            return 0
        taken = 0
        for key, table in tables.items():
            if isinstance(key, tuple) and len(key) == 2 and all(isinstance(k, str) for k in key):
                if isinstance(table, FsmTable) and key[1] == table.type_name:
                    self._made.setdefault(key, table)
                    taken += 1
        return taken
