"""The demo cell is complete: every instance checked, over a client session, against its type tree.

The member resolution here is written independently of ``uacell.ua.instantiate.TypeIndex``: it reads
the type system from the server through the client (browse + read, batched and cached) and derives
what each instance must carry, including the members that a nested child's *own* type declares
(ExecuteState's Start, TaskControlStateMachine's LoadByName).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass
from pathlib import Path

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import first_start_source, free_port

from uacell.binding.cell import _NOISE, Part, demo_cell
from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.ua.instantiate import Selection

module_loop = pytest.mark.asyncio(loop_scope="module")

MANDATORY = ua.NodeId(78)
OPTIONAL = ua.NodeId(80)
MANDATORY_PLACEHOLDER = ua.NodeId(11510)
OPTIONAL_PLACEHOLDER = ua.NodeId(11508)
HAS_TYPE_DEFINITION = ua.NodeId(40)
HAS_MODELLING_RULE = ua.NodeId(37)
HAS_SUBTYPE = ua.NodeId(45)
HAS_ADDIN = ua.NodeId(17604)
HIERARCHICAL = ua.NodeId(33)
STATE_TYPE = ua.NodeId(2307)
TRANSITION_TYPE = ua.NodeId(2310)
CELL_NS_URI = "urn:uacell:cell"
_CHUNK = 200


@dataclass
class Info:
    """What the test knows about one node: its attributes and every reference, both directions."""

    node_class: ua.NodeClass
    browse_name: ua.QualifiedName
    data_type: ua.NodeId | None
    value_rank: int | None
    refs: list[ua.ReferenceDescription]

    def targets(self, ref_type: ua.NodeId, forward: bool = True) -> list[ua.NodeId]:
        return [r.NodeId for r in self.refs if r.IsForward == forward and r.ReferenceTypeId == ref_type]

    def target(self, ref_type: ua.NodeId) -> ua.NodeId | None:
        found = self.targets(ref_type)
        return found[0] if found else None


class Space:
    """A cached, batch-loaded view of the server's address space through one client session."""

    # set by the fixture that loads it: the namespace indexes (cell, and each model's by short name)
    # and each part's root node by part name
    cell_ns: int
    ns: dict[str, int]
    roots: dict[str, ua.NodeId]

    def __init__(self, client: Client) -> None:
        self.client = client
        self.nodes: dict[ua.NodeId, Info] = {}
        self.hierarchical: set[ua.NodeId] = set()

    async def load(self, ids: Iterable[ua.NodeId]) -> None:
        todo = [n for n in dict.fromkeys(ids) if n not in self.nodes]
        for start in range(0, len(todo), _CHUNK):
            chunk = todo[start : start + _CHUNK]
            bp = ua.BrowseParameters()
            bp.View = ua.ViewDescription()
            bp.RequestedMaxReferencesPerNode = 0
            for n in chunk:
                d = ua.BrowseDescription()
                d.NodeId = n
                d.BrowseDirection = ua.BrowseDirection.Both
                d.ReferenceTypeId = ua.NodeId(ua.ObjectIds.References)
                d.IncludeSubtypes = True
                d.NodeClassMask = 0
                d.ResultMask = ua.BrowseResultMask.All
                bp.NodesToBrowse.append(d)
            browsed = await self.client.uaclient.browse(bp)
            rp = ua.ReadParameters()
            attrs = (
                ua.AttributeIds.NodeClass,
                ua.AttributeIds.BrowseName,
                ua.AttributeIds.DataType,
                ua.AttributeIds.ValueRank,
            )
            for n in chunk:
                for a in attrs:
                    rp.NodesToRead.append(ua.ReadValueId(NodeId=n, AttributeId=a))
            values = await self.client.uaclient.read(rp)
            for i, n in enumerate(chunk):
                dv = values[4 * i : 4 * i + 4]
                assert browsed[i].StatusCode.is_good(), f"cannot browse {n}: {browsed[i].StatusCode}"
                self.nodes[n] = Info(
                    node_class=ua.NodeClass(dv[0].Value.Value),
                    browse_name=dv[1].Value.Value,
                    data_type=dv[2].Value.Value if dv[2].StatusCode.is_good() else None,
                    value_rank=dv[3].Value.Value if dv[3].StatusCode.is_good() else None,
                    refs=list(browsed[i].References),
                )

    async def get(self, n: ua.NodeId) -> Info:
        if n not in self.nodes:
            await self.load([n])
        return self.nodes[n]

    async def subtypes(self, root: ua.NodeId) -> set[ua.NodeId]:
        out, level = {root}, [root]
        while level:
            await self.load(level)
            level = [t for n in level for t in self.nodes[n].targets(HAS_SUBTYPE) if t not in out]
            out.update(level)
        return out

    async def init(self) -> None:
        self.hierarchical = await self.subtypes(HIERARCHICAL) - {HAS_SUBTYPE}

    def children(self, info: Info) -> list[ua.ReferenceDescription]:
        """Forward hierarchical references (HasSubtype aside)."""
        return [r for r in info.refs if r.IsForward and r.ReferenceTypeId in self.hierarchical]

    async def prefetch(self, roots: list[ua.NodeId]) -> None:
        """Load the instance trees and the type trees they need, level by level (few round trips)."""
        level, seen = list(roots), set(roots)
        while level:
            await self.load(level)
            nxt: list[ua.NodeId] = []
            for n in level:
                info = self.nodes[n]
                follow = [r.NodeId for r in self.children(info)]
                follow += info.targets(HAS_TYPE_DEFINITION) + info.targets(HAS_SUBTYPE, forward=False)
                for t in follow:
                    if t not in seen:
                        seen.add(t)
                        nxt.append(t)
            level = nxt

    async def type_chain(self, type_id: ua.NodeId) -> list[ua.NodeId]:
        chain, current = [], type_id
        while current is not None:
            chain.append(current)
            supers = (await self.get(current)).targets(HAS_SUBTYPE, forward=False)
            current = supers[0] if supers else None
        return chain

    async def is_subtype(self, type_id: ua.NodeId | None, base: ua.NodeId) -> bool:
        return type_id is not None and not type_id.is_null() and base in await self.type_chain(type_id)


@dataclass(frozen=True)
class Member:
    decl: ua.NodeId
    browse_name: ua.QualifiedName
    node_class: ua.NodeClass
    ref_type: ua.NodeId
    rule: ua.NodeId
    type_definition: ua.NodeId | None
    data_type: ua.NodeId | None
    value_rank: int | None


async def declared(space: Space, node: ua.NodeId) -> dict[tuple[int, str], Member]:
    """Instance declarations directly below a type or instance declaration: children with a rule."""
    out: dict[tuple[int, str], Member] = {}
    for ref in space.children(await space.get(node)):
        child = await space.get(ref.NodeId)
        rule = child.target(HAS_MODELLING_RULE)
        if rule is None:
            continue
        out[_key(child.browse_name)] = Member(
            ref.NodeId,
            child.browse_name,
            child.node_class,
            ref.ReferenceTypeId,
            rule,
            child.target(HAS_TYPE_DEFINITION),
            child.data_type,
            child.value_rank,
        )
    return out


async def members(space: Space, decl: ua.NodeId | None, type_id: ua.NodeId | None) -> list[Member]:
    """Members of a node: its type's (supertypes first, subtypes override), then its declaration's."""
    merged: dict[tuple[int, str], Member] = {}
    if type_id is not None:
        for t in reversed(await space.type_chain(type_id)):
            merged.update(await declared(space, t))
    if decl is not None:
        merged.update(await declared(space, decl))
    return list(merged.values())


async def addin_name(space: Space, member: Member) -> ua.QualifiedName:
    """An AddIn instance is named by its type's DefaultInstanceBrowseName, in the type's namespace."""
    for t in await space.type_chain(member.type_definition):
        for ref in space.children(await space.get(t)):
            if ref.BrowseName.Name == "DefaultInstanceBrowseName":
                value = await space.client.get_node(ref.NodeId).read_value()
                assert member.type_definition is not None  # the type chain was walked from it
                return ua.QualifiedName(value.Name, member.type_definition.NamespaceIndex)
    return member.browse_name


def _key(qn: ua.QualifiedName) -> tuple[int, str]:
    return (qn.NamespaceIndex, qn.Name)


def _fmt(qn: ua.QualifiedName) -> str:
    return f"{qn.NamespaceIndex}:{qn.Name}"


async def check_node(
    space: Space,
    node: ua.NodeId,
    decl: ua.NodeId | None,
    type_id: ua.NodeId | None,
    where: str,
    rel: str,
    selection: Selection,
    problems: list[str],
) -> None:
    """Compare one instance node's children with the members its declaration and type call for."""
    info = await space.get(node)
    children = {_key(r.BrowseName): r for r in space.children(info)}
    matched: set[tuple[int, str]] = set()
    placeholders: list[Member] = []
    for m in await members(space, decl, type_id):
        if m.rule in (MANDATORY_PLACEHOLDER, OPTIONAL_PLACEHOLDER):
            placeholders.append(m)
            continue
        if await space.is_subtype(m.type_definition, STATE_TYPE) or await space.is_subtype(
            m.type_definition, TRANSITION_TYPE
        ):
            continue  # states and transitions live on the type only; checked below the instance
        name = await addin_name(space, m) if m.ref_type == HAS_ADDIN else m.browse_name
        path = f"{rel}/{name.Name}" if rel else name.Name
        wanted = m.rule == MANDATORY or (m.rule == OPTIONAL and selection.wants(path))
        ref = children.get(_key(name))
        label = f"{where}/{path}"
        if not wanted:
            # An optional AddIn another companion applies with a subtype of the declared type is no
            # copying error: OPC 40001-1's MachineIdentificationType as DI's Identification
            # (OPC 40010-1 Annex C; docs/machinery.md).
            applied = (
                ref is not None
                and ref.ReferenceTypeId == HAS_ADDIN
                and m.type_definition is not None
                and await space.is_subtype(ref.TypeDefinition, m.type_definition)
                and ref.TypeDefinition != m.type_definition
            )
            if ref is not None and not applied:
                problems.append(f"{label}: optional member not requested but present")
            continue
        if ref is None:
            rule = "mandatory" if m.rule == MANDATORY else "requested optional"
            problems.append(f"{label}: {rule} member {_fmt(name)} missing")
            continue
        matched.add(_key(name))
        child = await space.get(ref.NodeId)
        if child.node_class != m.node_class:
            problems.append(f"{label}: NodeClass {child.node_class.name}, expected {m.node_class.name}")
        if ref.ReferenceTypeId != m.ref_type:
            problems.append(f"{label}: reached by {ref.ReferenceTypeId}, expected {m.ref_type}")
        actual_type = child.target(HAS_TYPE_DEFINITION)
        if actual_type != m.type_definition:
            problems.append(f"{label}: TypeDefinition {actual_type}, expected {m.type_definition}")
        if m.node_class == ua.NodeClass.Variable:
            if child.data_type != m.data_type:
                problems.append(f"{label}: DataType {child.data_type}, expected {m.data_type}")
            if child.value_rank != m.value_rank:
                problems.append(f"{label}: ValueRank {child.value_rank}, expected {m.value_rank}")
        await check_node(space, ref.NodeId, m.decl, m.type_definition, where, path, selection, problems)
    # What is left must fill a placeholder; a mandatory placeholder needs at least one.
    filled: dict[ua.NodeId, int] = {p.decl: 0 for p in placeholders}
    for name, ref in children.items():
        if name in matched:
            continue
        for p in placeholders:
            if ref.NodeClass == p.node_class and (
                p.type_definition is None or await space.is_subtype(ref.TypeDefinition, p.type_definition)
            ):
                filled[p.decl] += 1
                break
        else:
            # Extensions in the server's own namespace are allowed (OPC UA lets instances carry more,
            # e.g. Filler1's InjectFault); a stray name from a standard namespace is a copying error,
            # except a historized variable's Part 11 "HA Configuration" (HasHistoricalConfiguration).
            # So are AddIns another specification applies (HasAddIn, OPC 10000-3) and the folder
            # OPC 40001-1 keeps its building blocks in (docs/machinery.md).
            historical = ref.ReferenceTypeId == ua.NodeId(ua.ObjectIds.HasHistoricalConfiguration)
            add_in = ref.ReferenceTypeId == HAS_ADDIN or name == (space.ns["Machinery"], "MachineryBuildingBlocks")
            if name[0] != space.cell_ns and not add_in and not (historical and name == (0, "HA Configuration")):
                problems.append(f"{where}/{rel}: unexpected child {name[0]}:{name[1]}")
    for p in placeholders:
        if p.rule == MANDATORY_PLACEHOLDER and filled[p.decl] == 0:
            problems.append(f"{where}/{rel}: mandatory placeholder {_fmt(p.browse_name)} has no instance")


async def _serve_cell(base: Path, cell: str, from_snapshot: bool) -> AsyncIterator[Space]:
    """A server with the shipped cell ``cell`` (demo or example), seen through one client session.

    Its own cache directory: ``from_snapshot`` starts (and stops) a first server that writes the
    address-space snapshot there, so that the checked one starts from it; otherwise the checked
    server builds its address space from the NodeSets.
    """
    config = fast_config(base / "data")
    config.server.cache_dir = base / "cache"
    config.cell = load_cell(builtin_cell_path(cell))
    if from_snapshot:
        first = await start_app(config)
        await first.snapshot_written()
        await first.stop()
        config.server.port = free_port()
    app = await start_app(config)
    assert app.address_space_source == ("snapshot" if from_snapshot else first_start_source())
    # The health probe (a ServerStatus read) gets 30 s, not 1 s: a loaded machine must not drop the session.
    client = Client(app.endpoint, timeout=60, watchdog_intervall=30.0)
    try:
        await client.connect()
        s = Space(client)
        await s.init()
        s.cell_ns = await client.get_namespace_index(CELL_NS_URI)
        s.ns = {
            key: await client.get_namespace_index(uri)
            for key, uri in (
                ("DI", "http://opcfoundation.org/UA/DI/"),
                ("Robotics", "http://opcfoundation.org/UA/Robotics/"),
                ("PackML", "http://opcfoundation.org/UA/PackML/"),
                ("Machinery", "http://opcfoundation.org/UA/Machinery/"),
            )
        }
        s.roots = {}
        for root, part in config.cell.parts():
            folder = f"{s.ns['DI']}:DeviceSet" if root == "DeviceSet" else f"{s.ns['PackML']}:PackMLObjects"
            s.roots[part.name] = (await client.nodes.objects.get_child([folder, f"{s.cell_ns}:{part.name}"])).nodeid
        await s.prefetch(list(s.roots.values()))
        yield s
    finally:
        await client.disconnect()
        await app.stop()


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def space(tmp_path_factory) -> AsyncIterator[Space]:
    """One demo-cell server for the module, started from an address-space snapshot."""
    async for s in _serve_cell(Path(tmp_path_factory.mktemp("completeness")), "demo", from_snapshot=True):
        yield s


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def example_space(tmp_path_factory) -> AsyncIterator[Space]:
    """One server with the larger shipped example cell for the module, built from the NodeSets."""
    async for s in _serve_cell(Path(tmp_path_factory.mktemp("completeness-example")), "example", from_snapshot=False):
        yield s


def _parts(cell: list[tuple[str, Part]]) -> list[tuple[str, Part, tuple[str, ...]]]:
    """Every part of a cell with the BrowseName path (names only) to it from its root."""
    out: list[tuple[str, Part, tuple[str, ...]]] = []

    def walk(root: str, part: Part, path: tuple[str, ...]) -> None:
        out.append((root, part, path))
        for child in part.children:
            walk(root, child, (*path, *[f for f in child.folder.split("/") if f], child.name))

    for _, part in cell:
        walk(part.name, part, ())
    return out


PARTS = _parts(demo_cell())
EXAMPLE_PARTS = _parts(load_cell(builtin_cell_path("example")).parts())


async def _child_by_name(space: Space, node: ua.NodeId, name: str) -> ua.NodeId:
    hits = [r.NodeId for r in space.children(await space.get(node)) if r.BrowseName.Name == name]
    assert len(hits) == 1, f"{node} has {len(hits)} children called {name}"
    return hits[0]


async def _part_node(space: Space, root: str, path: tuple[str, ...]) -> ua.NodeId:
    node = space.roots[root]
    for name in path:
        node = await _child_by_name(space, node, name)
    return node


def test_demo_cell_has_the_instances_of_design_md():
    names = {p.name for _, p, _ in PARTS}
    assert {"Robot1", "Controller1", "TaskControl1", "Arm1", "Filler1"} <= names
    assert {f"Axis{i}" for i in range(1, 7)} <= names
    assert {f"PowerTrain{i}" for i in range(1, 7)} <= names


async def _check_part(space: Space, root: str, part: Part, path: tuple[str, ...]) -> None:
    node = await _part_node(space, root, path)
    info = await space.get(node)
    type_id = info.target(HAS_TYPE_DEFINITION)
    type_name = (await space.get(type_id)).browse_name
    assert info.node_class == ua.NodeClass.Object
    assert type_name == ua.QualifiedName(part.type_name, space.ns[part.model])
    problems: list[str] = []
    # The members a part asks for: its Optional ones plus those its configuration gives values.
    selection = Selection((*part.include, *part.values), _NOISE)
    await check_node(space, node, None, type_id, "/".join((root, *path)), "", selection, problems)
    assert not problems, f"{len(problems)} problems:\n" + "\n".join(problems[:40])


@module_loop
@pytest.mark.parametrize(("root", "part", "path"), PARTS, ids=[p.name for _, p, _ in PARTS])
async def test_instance_is_complete_against_its_type_tree(space, root, part, path):
    await _check_part(space, root, part, path)


@module_loop
@pytest.mark.parametrize(("root", "part", "path"), EXAMPLE_PARTS, ids=["/".join((r, *p)) for r, _, p in EXAMPLE_PARTS])
async def test_example_instance_is_complete_against_its_type_tree(example_space, root, part, path):
    await _check_part(example_space, root, part, path)


def test_example_cell_has_the_parts_it_promises():
    names = {"/".join((r, *p)) for r, _, p in EXAMPLE_PARTS}
    assert {
        "Welder/Controllers/ControllerA/TaskControls/Seam",
        "Welder/Controllers/ControllerA/TaskControls/Service",
        "Welder/Controllers/ControllerB/TaskControls/Seam",
        "Welder/Controllers/ControllerB/TaskControls/Cleaning",
        "Handler/Controllers/Controller1/TaskControls/Palletize",
        "Filler",
        "Capper",
        "Labeler",
    } <= names
    assert {f"Welder/MotionDevices/ArmB/Axes/J{i}" for i in range(1, 8)} <= names
    assert "Welder/MotionDevices/ArmB/PowerTrains/PowerTrain7/Motor7" in names


async def _walk_for_placeholders(space: Space, root: str) -> None:
    bad: list[str] = []
    todo, seen = [(space.roots[root], root)], set()
    count = 0
    while todo:
        node, where = todo.pop()
        for ref in space.children(await space.get(node)):
            count += 1
            label = f"{where}/{ref.BrowseName.Name}"
            if ref.BrowseName.Name.startswith("<") or ref.BrowseName.Name.endswith(">"):
                bad.append(f"{label}: placeholder name")
            if await space.is_subtype(ref.TypeDefinition, STATE_TYPE):
                bad.append(f"{label}: State object copied (type {ref.TypeDefinition})")
            if await space.is_subtype(ref.TypeDefinition, TRANSITION_TYPE):
                bad.append(f"{label}: Transition object copied (type {ref.TypeDefinition})")
            # Only the cell's own nodes are the instance; references out of it are not walked.
            if ref.NodeId.NamespaceIndex == space.cell_ns and ref.NodeId not in seen:
                seen.add(ref.NodeId)
                todo.append((ref.NodeId, label))
    assert count > 100  # the walk really went through the instance
    assert not bad, "\n".join(bad)


@module_loop
@pytest.mark.parametrize("root", ["Robot1", "Filler1"])
async def test_no_placeholder_names_and_no_states_or_transitions_below(space, root):
    await _walk_for_placeholders(space, root)


@module_loop
@pytest.mark.parametrize("root", ["Welder", "Handler", "Filler", "Capper", "Labeler"])
async def test_example_has_no_placeholder_names_and_no_states_or_transitions_below(example_space, root):
    await _walk_for_placeholders(example_space, root)


@module_loop
async def test_identification_from_the_configuration_is_served(example_space):
    welder = await _node(example_space, "Welder")
    di = example_space.ns["DI"]
    assert (await (await welder.get_child(f"{di}:Manufacturer")).read_value()).Text == "uacell"
    assert (await (await welder.get_child(f"{di}:SerialNumber")).read_value()) == "EX-W-0001"
    assert (await (await welder.get_child(f"{di}:ProductInstanceUri")).read_value()) == "urn:uacell:example:Welder"
    arm = await _node(example_space, "Welder", "MotionDevices", "ArmB")
    assert (await (await arm.get_child(f"{di}:Model")).read_value()).Text == "Simulated seven-axis arm"
    controller = await _node(example_space, "Welder", "Controllers", "ControllerA")
    assert (await (await controller.get_child(f"{di}:SoftwareRevision")).read_value()) == "1.0"


# Usage-like spot checks, through the plain Node API.


async def _node(space: Space, *names: str):
    node = space.client.get_node(space.roots[names[0]])
    for name in names[1:]:
        node = space.client.get_node(await _child_by_name(space, node.nodeid, name))
    return node


@module_loop
async def test_task_control_state_machine_has_load_by_node_id_taking_an_expanded_node_id(space):
    sm = await _node(
        space,
        "Robot1",
        "Controllers",
        "Controller1",
        "TaskControls",
        "TaskControl1",
        "TaskControlOperation",
        "TaskControlStateMachine",
    )
    names = {(await c.read_browse_name()).Name for c in await sm.get_children()}
    assert {
        "LoadByNodeId",
        "LoadByName",
        "UnloadProgram",
        "UnloadByNodeId",
        "UnloadByName",
        "Start",
        "Stop",
        "ReadySubstateMachine",
    } <= names
    ready = await sm.get_child(f"{space.ns['Robotics']}:ReadySubstateMachine")
    assert await ready.get_child(f"{space.ns['Robotics']}:ResetToProgramStart")
    args = await (await sm.get_child(f"{space.ns['Robotics']}:LoadByNodeId")).get_child("0:InputArguments")
    value = await args.read_value()
    assert [(a.Name, a.DataType, a.ValueRank) for a in value] == [("Id", ua.NodeId(ua.ObjectIds.ExpandedNodeId), -1)]


@module_loop
async def test_execute_state_start_takes_packml_descriptors(space):
    execute = await _node(space, "Filler1", "BaseStateMachine", "MachineState", "ExecuteState")
    assert (await execute.read_type_definition()).NamespaceIndex == space.ns["PackML"]
    names = {(await c.read_browse_name()).Name for c in await execute.get_children()}
    assert {"Start", "Hold", "Unhold", "Suspend", "Unsuspend", "Reset", "ToComplete"} <= names
    start = await execute.get_child(f"{space.ns['PackML']}:Start")
    value = await (await start.get_child("0:InputArguments")).read_value()
    assert [(a.Name, a.DataType, a.ValueRank) for a in value] == [("Parameter", ua.NodeId(16, space.ns["PackML"]), 1)]


@module_loop
async def test_system_operation_is_named_in_the_robotics_namespace(space):
    controller = await _node(space, "Robot1", "Controllers", "Controller1")
    refs = await controller.get_references(refs=ua.ObjectIds.HierarchicalReferences)
    hits = [r for r in refs if r.BrowseName.Name == "SystemOperation"]
    assert [r.BrowseName.NamespaceIndex for r in hits] == [space.ns["Robotics"]]


@module_loop
async def test_task_control_operation_is_an_addin(space):
    task_control = await _node(space, "Robot1", "Controllers", "Controller1", "TaskControls", "TaskControl1")
    refs = await task_control.get_references(
        refs=HAS_ADDIN, direction=ua.BrowseDirection.Forward, includesubtypes=False
    )
    assert [r.BrowseName for r in refs] == [ua.QualifiedName("TaskControlOperation", space.ns["Robotics"])]
