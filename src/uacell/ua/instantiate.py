"""Deep, type-driven instantiation.

asyncua's ``instantiate`` copies the instance declarations below a type but misses the members that
a nested child's *own* type declares (an ExecuteState without Start, a TaskControlStateMachine
without LoadByName), and it turns placeholders such as ``<TaskModule>`` into real nodes. This module
builds an instance from the type system instead:

- the members of a node are those of its type and every supertype (a subtype's declaration wins by
  BrowseName), overlaid by the children the instance declaration itself declares;
- every Mandatory member is created, an Optional one when the ``Selection`` asks for it;
- placeholders (``MandatoryPlaceholder``/``OptionalPlaceholder``) are never created; the caller adds
  named instances in their place;
- AddIns (``HasAddIn``) are named by the AddIn type's ``DefaultInstanceBrowseName``;
- State and Transition objects are never copied (most carry no ModellingRule, but PackML's
  ``Cleared`` state is Optional: they are recognised by StateType/TransitionType).

It works directly on asyncua's address space, which keeps start-up fast. What it makes of a type
the first time is kept as a ``Template``: a later instance of the same type and selection is a copy
of it (no type walked, none of the type's nodes loaded from a snapshot), node for node what walking
the types again would make. The templates of what binders make at every start are kept in the
address-space snapshot (``Instantiator.kept_templates``).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import re
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from asyncua import Server, ua
from asyncua.server.address_space import AddressSpace, AttributeValue, NodeData

from uacell.ua import toolkit

log = logging.getLogger(__name__)

MANDATORY = 78
OPTIONAL = 80
OPTIONAL_PLACEHOLDER = 11508
MANDATORY_PLACEHOLDER = 11510
HAS_ADDIN = 17604
_HAS_ADDIN_ID = ua.NodeId(HAS_ADDIN)
_HAS_MODELLING_RULE = 37
_HAS_TYPE_DEFINITION = 40
_REF_IDS = {i: ua.NodeId(i) for i in (_HAS_MODELLING_RULE, _HAS_TYPE_DEFINITION)}
_STATE_LIKE = (ua.NodeId(2307), ua.NodeId(2310))  # StateType, TransitionType: the type's, not instances'
_AGGREGATES = 44
_ORGANIZES = 35
_DEFAULT_INSTANCE_BROWSE_NAME = "DefaultInstanceBrowseName"
_A = ua.AttributeIds


@dataclass(frozen=True)
class Member:
    """One instance declaration that an instance may carry."""

    decl: ua.NodeId
    browse_name: ua.QualifiedName
    node_class: ua.NodeClass
    reference_type: ua.NodeId
    rule: int | None
    type_definition: ua.NodeId | None

    @property
    def is_placeholder(self) -> bool:
        return self.rule in (OPTIONAL_PLACEHOLDER, MANDATORY_PLACEHOLDER)


@dataclass
class Selection:
    """Which Optional members to create, as glob patterns over BrowseName paths.

    A path is the chain of BrowseNames (without namespace prefixes) from the instance root, joined
    with ``/``: ``TaskControlOperation/TaskControlStateMachine/LoadByName``. ``*`` matches within a
    name, ``**`` matches any number of levels.
    """

    include: tuple[str, ...] = ()
    exclude: tuple[str, ...] = ()
    _cache: dict[str, bool] = field(default_factory=dict, repr=False)

    def wants(self, path: str) -> bool:
        hit = self._cache.get(path)
        if hit is None:
            hit = any(_match(path, p) for p in self.include) and not any(_match(path, p) for p in self.exclude)
            self._cache[path] = hit
        return hit


def _match(path: str, pattern: str) -> bool:
    return _compile(pattern).fullmatch(path) is not None


@functools.cache
def _compile(pattern: str) -> re.Pattern[str]:
    """``*``/``?`` stay within one name; ``**`` spans any number of names (zero included, but a
    trailing ``**`` needs at least one, so ``A/**`` means "below A")."""
    segments = pattern.split("/")
    out = []
    for i, seg in enumerate(segments):
        last = i == len(segments) - 1
        if seg == "**":
            out.append(".+" if last else "(?:[^/]+/)*")
            continue
        out.append("".join("[^/]*" if c == "*" else "[^/]" if c == "?" else re.escape(c) for c in seg))
        if not last:
            out.append("/")
    return re.compile("".join(out))


# (type, the Selection's include, its exclude): what a template is made for
TemplateKey = tuple[ua.NodeId, tuple[str, ...], tuple[str, ...]]


@dataclass(frozen=True)
class TemplateNode:
    """One member node of a template: its NodeId is the instance's path + ``suffix``.

    ``references`` pair each reference with the suffix of its target where the target is the
    instance or one of its members ("" the instance itself), None where it is outside (a type)."""

    suffix: str
    attributes: dict[ua.AttributeIds, ua.DataValue]
    references: list[tuple[ua.ReferenceDescription, str | None]]
    declaration: ua.NodeId


@dataclass(frozen=True)
class Template:
    """The members ``Instantiator.create`` made below an instance of one type and selection, in
    the order it made them, and the references it added to the instance itself."""

    nodes: tuple[TemplateNode, ...]
    root_references: tuple[tuple[ua.ReferenceDescription, str], ...]


class TypeIndex:
    """Questions about the type system, answered from asyncua's address space and cached."""

    def __init__(self, aspace: AddressSpace) -> None:
        self.aspace = aspace
        self._members: dict[ua.NodeId, list[Member]] = {}
        self._chains: dict[ua.NodeId, tuple[ua.NodeId, ...]] = {}
        self._member_refs = toolkit.subtypes(aspace, ua.NodeId(_AGGREGATES)) | {ua.NodeId(_ORGANIZES)}

    def attr(self, node: ua.NodeId, attribute: ua.AttributeIds) -> Any:
        value = self.aspace[node].attributes.get(attribute)
        return None if value is None or value.value is None or value.value.Value is None else value.value.Value.Value

    def supertype(self, type_id: ua.NodeId) -> ua.NodeId | None:
        return toolkit.supertype(self.aspace, type_id)

    def type_chain(self, type_id: ua.NodeId) -> tuple[ua.NodeId, ...]:
        """``type_id`` and its supertypes, most derived first."""
        chain = self._chains.get(type_id)
        if chain is None:
            found: list[ua.NodeId] = []
            current: ua.NodeId | None = type_id
            while current is not None and current in self.aspace:
                found.append(current)
                current = self.supertype(current)
            chain = self._chains[type_id] = tuple(found)
        return chain

    def is_subtype(self, type_id: ua.NodeId, base: ua.NodeId) -> bool:
        return base in self.type_chain(type_id)

    def _target(self, node: ua.NodeId, ref_type: int) -> ua.NodeId | None:
        ref_id = _REF_IDS[ref_type]
        for ref in self.aspace[node].references:
            if ref.IsForward and ref.ReferenceTypeId == ref_id:
                return ref.NodeId
        return None

    def type_definition(self, node: ua.NodeId) -> ua.NodeId | None:
        return self._target(node, _HAS_TYPE_DEFINITION)

    def rule(self, node: ua.NodeId) -> int | None:
        target = self._target(node, _HAS_MODELLING_RULE)
        return None if target is None else target.Identifier

    def declared_children(self, node: ua.NodeId) -> list[Member]:
        """The children that ``node`` itself declares (with a ModellingRule)."""
        out: list[Member] = []
        for ref in self.aspace[node].references:
            if not ref.IsForward or ref.ReferenceTypeId not in self._member_refs:
                continue
            if ref.NodeId not in self.aspace:
                continue
            rule = self.rule(ref.NodeId)
            if rule is None:
                continue  # States, Transitions and other type-only nodes
            out.append(
                Member(
                    decl=ref.NodeId,
                    browse_name=self.attr(ref.NodeId, _A.BrowseName),
                    node_class=ua.NodeClass(self.attr(ref.NodeId, _A.NodeClass)),
                    reference_type=ref.ReferenceTypeId,
                    rule=rule,
                    type_definition=self.type_definition(ref.NodeId),
                )
            )
        return out

    def type_members(self, type_id: ua.NodeId) -> list[Member]:
        """Members of a type including its supertypes; the most derived declaration wins by name."""
        cached = self._members.get(type_id)
        if cached is None:
            merged: dict[str, Member] = {}
            for t in reversed(self.type_chain(type_id)):
                for m in self.declared_children(t):
                    merged[m.browse_name.Name] = m
            cached = self._members[type_id] = list(merged.values())
        return cached

    def members(self, decl: ua.NodeId | None, type_id: ua.NodeId | None) -> list[Member]:
        """Members of an instance declared by ``decl`` of type ``type_id``: type's, overlaid by decl's."""
        merged: dict[str, Member] = {}
        if type_id is not None:
            for m in self.type_members(type_id):
                merged[m.browse_name.Name] = m
        if decl is not None:
            for m in self.declared_children(decl):
                merged[m.browse_name.Name] = m
        return list(merged.values())

    def addin_name(self, member: Member) -> ua.QualifiedName:
        """An AddIn's BrowseName: its type's DefaultInstanceBrowseName, in the AddIn type's namespace.

        (Robotics 1.02's SystemOperationType gives the name with the wrong namespace index; the
        AddIn type's own namespace is what the specification means.)
        """
        if member.type_definition is None:
            return member.browse_name
        for t in self.type_chain(member.type_definition):
            prop = toolkit.find_child(self.aspace, t, _DEFAULT_INSTANCE_BROWSE_NAME)
            if prop is not None:
                value = self.attr(prop, _A.Value)
                if isinstance(value, ua.QualifiedName) and value.Name:
                    return ua.QualifiedName(value.Name, member.type_definition.NamespaceIndex)
        return member.browse_name


class Instantiator:
    """Creates instances in one namespace, with NodeIds derived from their BrowseName paths."""

    def __init__(self, server: Server, namespace_index: int) -> None:
        self.server = server
        self.ns = namespace_index
        self.types = TypeIndex(server.iserver.aspace)
        self._svc = server.iserver.node_mgt_service
        # instance node -> the instance declaration it was made from (methods use it to find
        # their standard definition)
        self.declarations: dict[ua.NodeId, ua.NodeId] = {}
        self.templates: dict[TemplateKey, Template] = {}
        self._keeping = False  # ``keep_templates`` was called
        self._kept: set[TemplateKey] = set()
        self.copied = 0  # instances made from a template, and
        self.walked = 0  # by walking their types (tests)

    def keep_templates(self) -> None:
        """From now on, what is made is made again at every start (by binders, after the cell was
        built): ``kept_templates`` has its templates, for the address-space snapshot."""
        self._keeping = True

    def kept_templates(self) -> dict[TemplateKey, Template]:
        return {key: self.templates[key] for key in self._kept if key in self.templates}

    def nodeid(self, path: str) -> ua.NodeId:
        """The NodeId of the instance at ``path`` (as ``create`` makes it)."""
        return ua.NodeId(path, self.ns)

    def create(
        self,
        parent: ua.NodeId,
        type_id: ua.NodeId,
        name: str | ua.QualifiedName,
        selection: Selection | None = None,
        *,
        reference_type: ua.NodeId | int = ua.ObjectIds.HasComponent,
        path: str | None = None,
    ) -> ua.NodeId:
        """Create an Object of ``type_id`` called ``name`` below ``parent`` with all its members."""
        selection = selection or Selection()
        qname = name if isinstance(name, ua.QualifiedName) else ua.QualifiedName(name, self.ns)
        base = path or qname.Name
        nodeid = self.nodeid(base)
        key: TemplateKey = (type_id, selection.include, selection.exclude)
        if self._keeping:
            self._kept.add(key)
        template = self.templates.get(key)
        aspace = self.types.aspace
        self._add_object(parent, nodeid, qname, type_id, None, _as_nodeid(reference_type))
        if template is not None and not any(self.nodeid(base + n.suffix) in aspace for n in template.nodes):
            self._copy(template, nodeid, base)
            return nodeid
        self.walked += 1
        before = len(aspace[nodeid].references)
        made = self._fill(nodeid, base, "", None, type_id, selection, [])
        if made is not None and template is None:
            made_template = self._template(nodeid, base, made, before)
            if made_template is not None:
                self.templates[key] = made_template
        return nodeid

    def _template(
        self, root: ua.NodeId, base: str, made: list[tuple[ua.NodeId, ua.NodeId]], before: int
    ) -> Template | None:
        """What ``create`` just made below ``root`` (path ``base``) as a template (``made``: the members
        and their declarations, in the order they were made; ``before``: how many references the
        instance had before its members); None if the instance gained a reference to anything else."""
        aspace = self.types.aspace
        ns = self.ns
        prefix = base + "."

        def inside(target: ua.NodeId) -> str | None:
            if target.NamespaceIndex != ns or not isinstance(target.Identifier, str):
                return None
            if target.Identifier == base:
                return ""
            return target.Identifier[len(base) :] if target.Identifier.startswith(prefix) else None

        nodes = []
        for member, decl in made:
            suffix = member.Identifier[len(base) :]
            data = aspace[member]
            attributes = {attr: value.value for attr, value in data.attributes.items() if value.value is not None}
            references = [(dataclasses.replace(ref), inside(ref.NodeId)) for ref in data.references]
            nodes.append(TemplateNode(suffix, attributes, references, decl))
        root_refs = []
        for ref in aspace[root].references[before:]:
            suffix = inside(ref.NodeId)
            if not suffix:
                return None  # not what walking the type makes: no copy could make it
            root_refs.append((dataclasses.replace(ref), suffix))
        return Template(tuple(nodes), tuple(root_refs))

    def _copy(self, template: Template, root: ua.NodeId, base: str) -> None:
        """The members of ``template`` below the new instance ``root``, as ``_fill`` makes them:
        their own NodeIds, Values stamped now, references to the instance with its names."""
        aspace = self.types.aspace
        self.copied += 1
        root_data = aspace[root]
        names = {a: root_data.attributes[a].value.Value.Value for a in (_A.BrowseName, _A.DisplayName)}
        ids = {"": root}

        def retarget(ref: ua.ReferenceDescription, suffix: str | None) -> ua.ReferenceDescription:
            if suffix is None:
                return ref  # to a type: the same for every instance (asyncua never changes one in place)
            if suffix:
                return dataclasses.replace(ref, NodeId=ids[suffix])
            return dataclasses.replace(
                ref, NodeId=root, BrowseName=names[_A.BrowseName] or ref.BrowseName,
                DisplayName=names[_A.DisplayName] or ref.DisplayName,
            )  # fmt: skip

        now = datetime.now(UTC)
        server_now = now if aspace.force_server_timestamp else None
        for node in template.nodes:
            ids[node.suffix] = self.nodeid(base + node.suffix)
        for node in template.nodes:
            nodeid = ids[node.suffix]
            data = NodeData(nodeid)
            for attr, value in node.attributes.items():
                if attr == _A.NodeId:
                    value = dataclasses.replace(value, Value=ua.Variant(nodeid, ua.VariantType.NodeId))
                elif attr == _A.Value:
                    value = dataclasses.replace(value, SourceTimestamp=now, ServerTimestamp=server_now)
                data.attributes[attr] = AttributeValue(value)
            data.references = [retarget(ref, suffix) for ref, suffix in node.references]
            aspace[nodeid] = data
            self.declarations[nodeid] = node.declaration
        root_data.references.extend(retarget(ref, suffix) for ref, suffix in template.root_references)

    def _fill(
        self,
        nodeid: ua.NodeId,
        id_path: str,
        rel_path: str,
        decl: ua.NodeId | None,
        type_id: ua.NodeId | None,
        selection: Selection,
        made: list[tuple[ua.NodeId, ua.NodeId]] | None,
    ) -> list[tuple[ua.NodeId, ua.NodeId]] | None:
        """Make the members of ``nodeid``; ``made`` collects each one made and its declaration, and
        becomes None (no template) when a member was there already."""
        for member in self.types.members(decl, type_id):
            state_like = any(self.types.is_subtype(member.type_definition, t) for t in _STATE_LIKE)
            if member.is_placeholder or state_like:
                continue
            qname = member.browse_name
            if member.reference_type == _HAS_ADDIN_ID:
                qname = self.types.addin_name(member)
            rel = f"{rel_path}/{qname.Name}" if rel_path else qname.Name
            if member.rule != MANDATORY and not selection.wants(rel):
                continue
            child = self.nodeid(f"{id_path}.{qname.Name}")
            if child in self.types.aspace:
                made = None
                continue
            self._add_member(nodeid, child, qname, member)
            self.declarations[child] = member.decl
            if made is not None:
                made.append((child, member.decl))
            made = self._fill(
                child, f"{id_path}.{qname.Name}", rel, member.decl, member.type_definition, selection, made
            )
        return made

    def _add_member(self, parent: ua.NodeId, nodeid: ua.NodeId, qname: ua.QualifiedName, m: Member) -> None:
        t = self.types
        if m.node_class == ua.NodeClass.Object:
            self._add_object(parent, nodeid, qname, m.type_definition, m.decl, m.reference_type)
        elif m.node_class == ua.NodeClass.Variable:
            attrs = ua.VariableAttributes()
            self._common(attrs, m.decl)
            value = t.aspace[m.decl].attributes.get(_A.Value)
            attrs.Value = value.value.Value if value is not None and value.value is not None else ua.Variant()
            attrs.DataType = t.attr(m.decl, _A.DataType) or ua.NodeId(ua.ObjectIds.BaseDataType)
            attrs.ValueRank = t.attr(m.decl, _A.ValueRank) if t.attr(m.decl, _A.ValueRank) is not None else -2
            attrs.ArrayDimensions = t.attr(m.decl, _A.ArrayDimensions) or []
            attrs.AccessLevel = t.attr(m.decl, _A.AccessLevel) or ua.AccessLevel.CurrentRead.mask
            attrs.UserAccessLevel = attrs.AccessLevel
            attrs.MinimumSamplingInterval = t.attr(m.decl, _A.MinimumSamplingInterval) or 0.0
            attrs.Historizing = False
            attrs.SpecifiedAttributes = _mask(
                "DisplayName",
                "Description",
                "Value",
                "DataType",
                "ValueRank",
                "ArrayDimensions",
                "AccessLevel",
                "UserAccessLevel",
                "MinimumSamplingInterval",
                "Historizing",
                "WriteMask",
                "UserWriteMask",
            )
            self._add(parent, nodeid, qname, ua.NodeClass.Variable, attrs, m.type_definition, m.reference_type)
        elif m.node_class == ua.NodeClass.Method:
            attrs = ua.MethodAttributes()
            self._common(attrs, m.decl)
            attrs.Executable = True
            attrs.UserExecutable = True
            attrs.SpecifiedAttributes = _mask(
                "DisplayName", "Description", "Executable", "UserExecutable", "WriteMask", "UserWriteMask"
            )
            self._add(parent, nodeid, qname, ua.NodeClass.Method, attrs, None, m.reference_type)
        else:
            log.debug("not instantiating %s member %s", m.node_class, qname)

    def _add_object(
        self,
        parent: ua.NodeId,
        nodeid: ua.NodeId,
        qname: ua.QualifiedName,
        type_id: ua.NodeId | None,
        decl: ua.NodeId | None,
        reference_type: ua.NodeId,
    ) -> None:
        attrs = ua.ObjectAttributes()
        if decl is not None:
            self._common(attrs, decl)
            attrs.EventNotifier = self.types.attr(decl, _A.EventNotifier) or 0
        else:
            attrs.DisplayName = ua.LocalizedText(qname.Name)
            attrs.Description = ua.LocalizedText()
            attrs.EventNotifier = 0
        attrs.SpecifiedAttributes = _mask("DisplayName", "Description", "EventNotifier", "WriteMask", "UserWriteMask")
        self._add(parent, nodeid, qname, ua.NodeClass.Object, attrs, type_id, reference_type)

    def _common(self, attrs: Any, decl: ua.NodeId) -> None:
        attrs.DisplayName = self.types.attr(decl, _A.DisplayName) or ua.LocalizedText()
        attrs.Description = self.types.attr(decl, _A.Description) or ua.LocalizedText()
        attrs.WriteMask = 0
        attrs.UserWriteMask = 0

    def _add(
        self,
        parent: ua.NodeId,
        nodeid: ua.NodeId,
        qname: ua.QualifiedName,
        node_class: ua.NodeClass,
        attrs: Any,
        type_id: ua.NodeId | None,
        reference_type: int,
    ) -> None:
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nodeid
        item.BrowseName = qname
        item.NodeClass = node_class
        item.ParentNodeId = parent
        item.ReferenceTypeId = reference_type
        item.TypeDefinition = type_id or ua.NodeId()
        item.NodeAttributes = attrs
        (result,) = self._svc.add_nodes([item])
        if not result.StatusCode.is_good():
            raise RuntimeError(f"cannot create {nodeid} ({qname.Name}): {result.StatusCode}")

    def reference(
        self, source: ua.NodeId, target: ua.NodeId, kind: ua.NodeId | int, target_class: ua.NodeClass
    ) -> None:
        """A forward reference of type ``kind`` from ``source`` to ``target`` (and its inverse)."""
        item = ua.AddReferencesItem(
            SourceNodeId=source,
            TargetNodeId=target,
            ReferenceTypeId=_as_nodeid(kind),
            IsForward=True,
            TargetNodeClass=target_class,
        )
        (status,) = self._svc.add_references([item])
        if not status.is_good():
            raise RuntimeError(f"cannot reference {target} from {source}: {status}")


def _as_nodeid(ref: ua.NodeId | int) -> ua.NodeId:
    return ref if isinstance(ref, ua.NodeId) else ua.NodeId(ref)


def _mask(*names: str) -> int:
    out = 0
    for n in names:
        out |= getattr(ua.NodeAttributesMask, n)
    return out
