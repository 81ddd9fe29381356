"""Selection patterns and the deep Instantiator, on a small hand-written type system."""

from __future__ import annotations

import textwrap
from collections.abc import AsyncIterator
from datetime import UTC, datetime

import pytest
import pytest_asyncio
from asyncua import Server, ua

from uacell.ua.instantiate import Instantiator, Selection

module_loop = pytest.mark.asyncio(loop_scope="module")

# Selection


@pytest.mark.parametrize(
    ("pattern", "path", "wanted"),
    [
        ("Lock", "Lock", True),
        ("Lock", "Lock/InitLock", False),
        ("ParameterSet/*", "ParameterSet/Speed", True),
        ("ParameterSet/*", "ParameterSet/Speed/EURange", False),  # `*` stays within one name
        ("ParameterSet/*", "ParameterSet", False),
        ("*Lock", "InitLock", True),
        ("*Lock", "Lock/InitLock", False),
        ("Parameter*/Speed", "ParameterSet/Speed", True),
        ("TaskControlOperation/**", "TaskControlOperation/TaskControlStateMachine", True),
        ("TaskControlOperation/**", "TaskControlOperation/TaskControlStateMachine/LoadByName", True),
        ("TaskControlOperation/**", "TaskControlOperation", False),  # the folder itself is asked for apart
        ("TaskControlOperation/**", "SystemOperation/Start", False),
        ("**", "A", True),
        ("**", "A/B/C", True),
        ("**/CurrentState/Number", "X/Y/CurrentState/Number", True),
        ("**/CurrentState/Number", "X/CurrentState/Id", False),
        ("**/Last*/Number", "A/LastTransition/Number", True),
        ("Lo?k", "Lock", True),
        ("Lo?k", "Lo/k", False),
    ],
)
def test_selection_patterns(pattern, path, wanted):
    assert Selection((pattern,)).wants(path) is wanted


@pytest.mark.parametrize(("pattern", "path"), [("**/CurrentState/Number", "CurrentState/Number"), ("A/**/Z", "A/Z")])
def test_double_star_matches_zero_levels(pattern, path):
    assert Selection((pattern,)).wants(path)


def test_single_star_stays_in_one_name_next_to_a_double_star():
    assert not Selection(("**/Last*/Number",)).wants("A/LastTransition/Id/Number")


def test_excludes_win_over_includes():
    s = Selection(("**",), ("**/EffectiveDisplayName", "SystemOperation/*/Stop"))
    assert s.wants("SystemOperation/SystemOperationStateMachine/Start")
    assert not s.wants("SystemOperation/SystemOperationStateMachine/Stop")
    assert not s.wants("A/CurrentState/EffectiveDisplayName")
    assert s.wants("A/CurrentState/EffectiveDisplayNameX")


def test_an_empty_selection_wants_nothing():
    assert not Selection().wants("Lock")
    assert not Selection((), ("**",)).wants("Lock")


# The Instantiator

_TYPES = """\
<UANodeSet xmlns="http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"
           xmlns:uax="http://opcfoundation.org/UA/2008/02/Types.xsd">
  <NamespaceUris><Uri>urn:uacell:test:types</Uri></NamespaceUris>
  <Aliases>
    <Alias Alias="Int32">i=6</Alias>
    <Alias Alias="Double">i=11</Alias>
    <Alias Alias="QualifiedName">i=20</Alias>
    <Alias Alias="Argument">i=296</Alias>
    <Alias Alias="HasModellingRule">i=37</Alias>
    <Alias Alias="HasTypeDefinition">i=40</Alias>
    <Alias Alias="HasSubtype">i=45</Alias>
    <Alias Alias="HasProperty">i=46</Alias>
    <Alias Alias="HasComponent">i=47</Alias>
    <Alias Alias="HasAddIn">i=17604</Alias>
  </Aliases>
  <UAObjectType NodeId="ns=1;i=1001" BrowseName="1:SubT">
    <DisplayName>SubT</DisplayName>
    <References>
      <Reference ReferenceType="HasSubtype" IsForward="false">i=58</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=6001</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=7001</Reference>
    </References>
  </UAObjectType>
  <UAVariable NodeId="ns=1;i=6001" BrowseName="1:SubM" ParentNodeId="ns=1;i=1001" DataType="Int32">
    <DisplayName>SubM</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=63</Reference>
      <Reference ReferenceType="HasModellingRule">i=78</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1001</Reference>
    </References>
  </UAVariable>
  <UAMethod NodeId="ns=1;i=7001" BrowseName="1:Run" ParentNodeId="ns=1;i=1001">
    <DisplayName>Run</DisplayName>
    <References>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1001</Reference>
    </References>
  </UAMethod>
  <UAObjectType NodeId="ns=1;i=1002" BrowseName="1:AddInT">
    <DisplayName>AddInT</DisplayName>
    <References>
      <Reference ReferenceType="HasSubtype" IsForward="false">i=58</Reference>
      <Reference ReferenceType="HasProperty">ns=1;i=6002</Reference>
    </References>
  </UAObjectType>
  <UAVariable NodeId="ns=1;i=6002" BrowseName="DefaultInstanceBrowseName" ParentNodeId="ns=1;i=1002"
              DataType="QualifiedName">
    <DisplayName>DefaultInstanceBrowseName</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=68</Reference>
      <Reference ReferenceType="HasProperty" IsForward="false">ns=1;i=1002</Reference>
    </References>
    <Value>
      <uax:QualifiedName xmlns:uax="http://opcfoundation.org/UA/2008/02/Types.xsd">
        <uax:NamespaceIndex>0</uax:NamespaceIndex>
        <uax:Name>Helper</uax:Name>
      </uax:QualifiedName>
    </Value>
  </UAVariable>
  <UAObjectType NodeId="ns=1;i=1003" BrowseName="1:ItemT">
    <DisplayName>ItemT</DisplayName>
    <References><Reference ReferenceType="HasSubtype" IsForward="false">i=58</Reference></References>
  </UAObjectType>
  <UAObjectType NodeId="ns=1;i=1010" BrowseName="1:BaseT">
    <DisplayName>BaseT</DisplayName>
    <References>
      <Reference ReferenceType="HasSubtype" IsForward="false">i=58</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=6010</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=6011</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=7010</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=5010</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=5011</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=5012</Reference>
      <Reference ReferenceType="HasAddIn">ns=1;i=5013</Reference>
    </References>
  </UAObjectType>
  <UAVariable NodeId="ns=1;i=6010" BrowseName="1:M" ParentNodeId="ns=1;i=1010" DataType="Int32">
    <DisplayName>M</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=63</Reference>
      <Reference ReferenceType="HasModellingRule">i=78</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1010</Reference>
    </References>
  </UAVariable>
  <UAVariable NodeId="ns=1;i=6011" BrowseName="1:O" ParentNodeId="ns=1;i=1010" DataType="Int32">
    <DisplayName>O</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=63</Reference>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1010</Reference>
    </References>
  </UAVariable>
  <UAMethod NodeId="ns=1;i=7010" BrowseName="1:Go" ParentNodeId="ns=1;i=1010">
    <DisplayName>Go</DisplayName>
    <References>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasProperty">ns=1;i=6012</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1010</Reference>
    </References>
  </UAMethod>
  <UAVariable NodeId="ns=1;i=6012" BrowseName="InputArguments" ParentNodeId="ns=1;i=7010" DataType="Argument"
              ValueRank="1" ArrayDimensions="0">
    <DisplayName>InputArguments</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=68</Reference>
      <Reference ReferenceType="HasModellingRule">i=78</Reference>
      <Reference ReferenceType="HasProperty" IsForward="false">ns=1;i=7010</Reference>
    </References>
  </UAVariable>
  <UAObject NodeId="ns=1;i=5010" BrowseName="1:Sub" ParentNodeId="ns=1;i=1010">
    <DisplayName>Sub</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">ns=1;i=1001</Reference>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasProperty">ns=1;i=6013</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1010</Reference>
    </References>
  </UAObject>
  <UAVariable NodeId="ns=1;i=6013" BrowseName="1:Extra" ParentNodeId="ns=1;i=5010" DataType="Double">
    <DisplayName>Extra</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=68</Reference>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasProperty" IsForward="false">ns=1;i=5010</Reference>
    </References>
  </UAVariable>
  <UAObject NodeId="ns=1;i=5011" BrowseName="1:&lt;Item&gt;" ParentNodeId="ns=1;i=1010">
    <DisplayName>&lt;Item&gt;</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">ns=1;i=1003</Reference>
      <Reference ReferenceType="HasModellingRule">i=11510</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1010</Reference>
    </References>
  </UAObject>
  <UAObject NodeId="ns=1;i=5012" BrowseName="1:Idle" ParentNodeId="ns=1;i=1010">
    <DisplayName>Idle</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=2309</Reference>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1010</Reference>
    </References>
  </UAObject>
  <UAObject NodeId="ns=1;i=5013" BrowseName="1:Addy" ParentNodeId="ns=1;i=1010">
    <DisplayName>Addy</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">ns=1;i=1002</Reference>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasAddIn" IsForward="false">ns=1;i=1010</Reference>
    </References>
  </UAObject>
  <UAObjectType NodeId="ns=1;i=1011" BrowseName="1:DerivedT">
    <DisplayName>DerivedT</DisplayName>
    <References>
      <Reference ReferenceType="HasSubtype" IsForward="false">ns=1;i=1010</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=6020</Reference>
      <Reference ReferenceType="HasComponent">ns=1;i=6021</Reference>
    </References>
  </UAObjectType>
  <UAVariable NodeId="ns=1;i=6020" BrowseName="1:D" ParentNodeId="ns=1;i=1011" DataType="Double">
    <DisplayName>D</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=63</Reference>
      <Reference ReferenceType="HasModellingRule">i=78</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1011</Reference>
    </References>
  </UAVariable>
  <UAVariable NodeId="ns=1;i=6021" BrowseName="1:O" ParentNodeId="ns=1;i=1011" DataType="Double"
              ValueRank="1" ArrayDimensions="0">
    <DisplayName>O</DisplayName>
    <References>
      <Reference ReferenceType="HasTypeDefinition">i=63</Reference>
      <Reference ReferenceType="HasModellingRule">i=80</Reference>
      <Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1011</Reference>
    </References>
  </UAVariable>
</UANodeSet>
"""


class Small:
    def __init__(self, server: Server, types_ns: int, cell_ns: int) -> None:
        self.server, self.types_ns, self.cell_ns = server, types_ns, cell_ns
        self.instantiator = Instantiator(server, cell_ns)

    def type(self, i: int) -> ua.NodeId:
        return ua.NodeId(i, self.types_ns)

    def q(self, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.types_ns)

    async def children(self, nodeid: ua.NodeId) -> dict[str, ua.ReferenceDescription]:
        refs = await self.server.get_node(nodeid).get_references(
            refs=ua.ObjectIds.HierarchicalReferences, direction=ua.BrowseDirection.Forward
        )
        return {r.BrowseName.to_string(): r for r in refs}

    async def tree(self, nodeid: ua.NodeId, prefix: str = "") -> set[str]:
        """Every BrowseName path (``ns:Name/ns:Name``) below ``nodeid``."""
        out: set[str] = set()
        for name, ref in (await self.children(nodeid)).items():
            path = f"{prefix}/{name}" if prefix else name
            out.add(path)
            out |= await self.tree(ref.NodeId, path)
        return out


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def small() -> AsyncIterator[Small]:
    server = Server()
    await server.init()
    await server.import_xml(xmlstring=textwrap.dedent(_TYPES))
    types_ns = await server.get_namespace_index("urn:uacell:test:types")
    cell_ns = await server.register_namespace("urn:uacell:test:cell")
    yield Small(server, types_ns, cell_ns)


OBJECTS = ua.NodeId(ua.ObjectIds.ObjectsFolder)


@module_loop
async def test_only_mandatory_members_without_a_selection(small):
    node = small.instantiator.create(OBJECTS, small.type(1011), "Bare")
    t = small.types_ns
    assert await small.tree(node) == {f"{t}:M", f"{t}:D"}
    assert node == ua.NodeId("Bare", small.cell_ns)
    assert await small.server.get_node(node).read_type_definition() == small.type(1011)


@module_loop
async def test_selected_members_with_the_members_of_nested_types(small):
    node = small.instantiator.create(OBJECTS, small.type(1011), "Thing", Selection(("O", "Sub", "Sub/**", "Go")))
    t = small.types_ns
    assert await small.tree(node) == {
        f"{t}:M",
        f"{t}:D",
        f"{t}:O",
        f"{t}:Go",
        f"{t}:Go/0:InputArguments",
        f"{t}:Sub",
        f"{t}:Sub/{t}:SubM",  # declared by SubT, the nested child's own type
        f"{t}:Sub/{t}:Run",
        f"{t}:Sub/{t}:Extra",  # declared by the instance declaration Sub itself
    }
    children = await small.children(node)
    sub = small.server.get_node(children[f"{t}:Sub"].NodeId)
    assert sub.nodeid == ua.NodeId("Thing.Sub", small.cell_ns)
    assert await sub.read_type_definition() == small.type(1001)
    assert await sub.read_node_class() == ua.NodeClass.Object
    # DerivedT's O (Double[]) overrides BaseT's O (Int32 scalar).
    o = small.server.get_node(children[f"{t}:O"].NodeId)
    assert (await o.read_data_type(), await o.read_value_rank()) == (ua.NodeId(ua.ObjectIds.Double), 1)
    m = small.server.get_node(children[f"{t}:M"].NodeId)
    assert (await m.read_data_type(), await m.read_value_rank()) == (ua.NodeId(ua.ObjectIds.Int32), -1)
    args = small.server.get_node(ua.NodeId("Thing.Go.InputArguments", small.cell_ns))
    assert await args.read_data_type() == ua.NodeId(ua.ObjectIds.Argument)
    assert await args.read_value_rank() == 1
    assert small.instantiator.declarations[m.nodeid] == small.type(6010)
    assert small.instantiator.declarations[o.nodeid] == small.type(6021)


@module_loop
async def test_excludes_leave_out_optional_members_deep_down(small):
    node = small.instantiator.create(OBJECTS, small.type(1011), "NoRun", Selection(("**",), ("**/Run", "Go")))
    t = small.types_ns
    paths = await small.tree(node)
    assert f"{t}:Sub/{t}:SubM" in paths and f"{t}:Sub/{t}:Extra" in paths
    assert not {p for p in paths if "Run" in p or "Go" in p}


@module_loop
async def test_placeholders_and_states_are_never_created(small):
    node = small.instantiator.create(OBJECTS, small.type(1011), "All", Selection(("**",)))
    paths = await small.tree(node)
    assert not [p for p in paths if "<" in p or "Idle" in p]
    assert f"{small.types_ns}:Helper" in paths  # `**` did select every optional member


@module_loop
async def test_addin_is_named_by_default_instance_browse_name_in_the_type_namespace(small):
    node = small.instantiator.create(OBJECTS, small.type(1010), "WithAddIn", Selection(("Helper",)))
    refs = await small.server.get_node(node).get_references(
        refs=17604, direction=ua.BrowseDirection.Forward, includesubtypes=False
    )
    assert [r.BrowseName for r in refs] == [small.q("Helper")]
    assert refs[0].TypeDefinition == small.type(1002)
    assert refs[0].NodeId == ua.NodeId("WithAddIn.Helper", small.cell_ns)


@module_loop
async def test_selection_paths_use_the_addin_name(small):
    # "Addy" is the declaration's BrowseName; the selection sees the instance's name only.
    node = small.instantiator.create(OBJECTS, small.type(1010), "ByDeclName", Selection(("Addy",)))
    assert await small.tree(node) == {f"{small.types_ns}:M"}


# Templates: a second instance of a type is a copy of what the first one's walk made


def _described(aspace, root: ua.NodeId) -> dict[str, object]:
    """Every node of the instance at ``root`` (NodeIds as suffixes of the root's path; the root's
    own names as "ROOT", so that two instances of one type compare equal), with the references of its
    parent to it. Value timestamps as "stamped" or None."""
    base: str = root.Identifier

    def name(node: ua.NodeId) -> object:
        ident = node.Identifier
        if node.NamespaceIndex == root.NamespaceIndex and isinstance(ident, str):
            if ident == base:
                return "ROOT"
            if ident.startswith(base + "."):
                return ident[len(base) :]
        return node

    def ref(r: ua.ReferenceDescription) -> tuple[object, ...]:
        names = tuple("ROOT" if n in names_of_root else n for n in (r.BrowseName, r.DisplayName))
        return (r.ReferenceTypeId, r.IsForward, name(r.NodeId), r.NodeClass, *names, r.TypeDefinition)

    def value(attr: ua.AttributeIds, dv: ua.DataValue) -> object:
        if attr == ua.AttributeIds.NodeId:
            return name(dv.Value.Value)
        if attr in (ua.AttributeIds.BrowseName, ua.AttributeIds.DisplayName) and dv.Value.Value in names_of_root:
            return "ROOT"
        stamped = (dv.SourceTimestamp is not None, dv.ServerTimestamp is not None)
        return (dv.Value, dv.StatusCode, stamped)

    root_data = aspace[root]
    names_of_root = [
        root_data.attributes[a].value.Value.Value for a in (ua.AttributeIds.BrowseName, ua.AttributeIds.DisplayName)
    ]
    out: dict[str, object] = {}
    pending = [root]
    while pending:
        node = pending.pop()
        data = aspace[node]
        out[str(name(node))] = (
            {attr: value(attr, av.value) for attr, av in data.attributes.items()},
            sorted((ref(r) for r in data.references), key=repr),
        )
        pending += [r.NodeId for r in data.references if r.IsForward and name(r.NodeId) not in (r.NodeId, "ROOT")]
    return out


@module_loop
async def test_a_second_instance_is_a_copy_of_what_walking_the_types_made_node_for_node(small):
    inst = small.instantiator
    selection = Selection(("**",), ("**/Run",))
    aspace = small.server.iserver.aspace
    first = inst.create(OBJECTS, small.type(1011), "Walked1", selection)
    copied_before = inst.copied
    before = datetime.now(UTC)
    copy = inst.create(OBJECTS, small.type(1011), "Copied", selection)
    assert inst.copied == copied_before + 1
    # its values are stamped when it was made, like any new node's
    stamps = [
        aspace[n].attributes[ua.AttributeIds.Value].value.SourceTimestamp
        for n in aspace.keys()
        if n.NamespaceIndex == small.cell_ns
        and str(n.Identifier).startswith("Copied.")
        and ua.AttributeIds.Value in aspace[n].attributes
    ]
    assert stamps and all(stamp >= before for stamp in stamps)
    # the same instance made by walking the types again, without the template
    key = (small.type(1011), selection.include, selection.exclude)
    template = inst.templates.pop(key)
    walked = inst.create(OBJECTS, small.type(1011), "Walked2", selection)
    assert inst.copied == copied_before + 1 and inst.templates[key] is not template  # walked, kept anew
    described = _described(aspace, walked)
    assert {".M", ".Sub.SubM", ".Helper", ".Go.InputArguments"} <= set(described)  # nested, AddIn, arguments
    assert _described(aspace, copy) == described == _described(aspace, first)
    # the Objects folder references each instance as asyncua's AddNodes made it
    refs = {r.NodeId: r for r in aspace[OBJECTS].references}
    assert refs[copy].BrowseName == ua.QualifiedName("Copied", small.cell_ns)
    assert refs[copy].TypeDefinition == refs[walked].TypeDefinition == small.type(1011)
    # the copy's members know their declarations (methods find their definitions by them)
    for suffix in (".M", ".Sub.SubM", ".Go.InputArguments"):
        member = ua.NodeId(copy.Identifier + suffix, small.cell_ns)
        assert inst.declarations[member] == inst.declarations[ua.NodeId(walked.Identifier + suffix, small.cell_ns)]
    # a copy's values are its own: writing one leaves the other instances' as they were
    m_copy, m_walked = (ua.NodeId(n.Identifier + ".M", small.cell_ns) for n in (copy, walked))
    await small.server.get_node(m_copy).write_value(ua.Variant(42, ua.VariantType.Int32))
    assert await small.server.get_node(m_copy).read_value() == 42
    assert await small.server.get_node(m_walked).read_value() != 42


@module_loop
async def test_an_instance_whose_members_exist_already_is_walked_and_makes_no_template(small):
    inst = small.instantiator
    selection = Selection(("Sub",))
    inst.create(OBJECTS, small.type(1011), "Partly1", selection)
    key = (small.type(1011), selection.include, selection.exclude)
    inst.templates.pop(key)
    # a member of the next instance is there before it: the walk skips it, no template is kept
    small.instantiator.create(OBJECTS, small.type(1001), "Partly2.Sub")
    copied = inst.copied
    node = inst.create(OBJECTS, small.type(1011), "Partly2", selection)
    assert inst.copied == copied and key not in inst.templates
    t = small.types_ns
    assert await small.tree(node) >= {f"{t}:M", f"{t}:D"}


@module_loop
async def test_templates_made_after_keep_templates_are_kept_and_survive_pickling(small):
    import pickle

    inst = Instantiator(small.server, small.cell_ns)
    inst.create(OBJECTS, small.type(1011), "BeforeKeeping", Selection(("O",)))
    inst.keep_templates()
    inst.create(OBJECTS, small.type(1001), "Kept1")
    kept = inst.kept_templates()
    assert list(kept) == [(small.type(1001), (), ())]  # made before keep_templates: not kept
    # another instantiator (a restart) copies from the kept templates, as pickled in a snapshot
    restarted = Instantiator(small.server, small.cell_ns)
    restarted.templates.update(pickle.loads(pickle.dumps(kept)))
    node = restarted.create(OBJECTS, small.type(1001), "Kept2")
    assert restarted.copied == 1
    aspace = small.server.iserver.aspace
    assert _described(aspace, node) == _described(aspace, ua.NodeId("Kept1", small.cell_ns))
