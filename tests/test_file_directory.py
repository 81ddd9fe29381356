"""FileDirectoryBinding through a real asyncua client over TCP: Controller1's Programs over a FileStore.

One server serves the whole module (starting one takes seconds); every test starts from the same
baseline directory and gets fresh client sessions with the role it asks for.
"""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import raw_call

from uacell.binding.file_directory import FILE_DIRECTORY_TYPE, FILE_TYPE, FileDirectoryBinding
from uacell.core.file_store import TEMP_PREFIX, Entry, FileStore
from uacell.core.roles import Role
from uacell.host import ServerView
from uacell.server import UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

PROGRAMS = "Robot1.Controllers.Controller1.Programs"
BASELINE = {"pick.robot": b"program Pick\nmove 1 2 3\n", "lib/gripper.robot": b"module Gripper\n"}
SAMPLES = {"a.robot": b"program A\n", "b.robot": b"program B\n"}
R, W, E = 1, 2, 4
Code = ua.StatusCodes


class Rig:
    app: UacellServer
    store: FileStore
    binding: FileDirectoryBinding
    samples: FileDirectoryBinding
    initial: dict[str, ua.NodeId]  # BrowseName -> TypeDefinition of Programs' children right after create
    ns: int
    clients: list[Client]

    def node(self, relpath: str) -> ua.NodeId:
        return self.binding.node_of(relpath)

    async def connect(self, role: Role = Role.ENGINEER) -> Client:
        """A new anonymous session with ``role`` (the role is fixed when the session activates)."""
        manager = self.app.server.iserver.user_manager
        manager.policy = dataclasses.replace(manager.policy, anonymous_role=role)
        client = Client(self.app.endpoint, timeout=30)
        await client.connect()
        self.clients.append(client)
        return client


def _write_baseline(root: Path) -> None:
    for relpath, content in BASELINE.items():
        path = root / relpath
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content)


async def _binder(app: ServerView, rig: Rig, programs: Path, samples: Path):
    ns = app.cell.instantiator.ns
    rig.ns = ns
    rig.store = FileStore(programs)
    rig.binding = await FileDirectoryBinding.create(app, ua.NodeId(PROGRAMS, ns), rig.store)
    aspace = app.server.iserver.aspace
    rig.initial = {
        ref.BrowseName.Name: ref.TypeDefinition
        for ref in aspace[ua.NodeId(PROGRAMS, ns)].references
        if ref.IsForward and ref.ReferenceTypeId == ua.NodeId(ua.ObjectIds.Organizes)
    }
    # The binding knows no companion: a second FileDirectoryType anywhere works the same way.
    samples_node = app.cell.instantiator.create(
        ua.NodeId(ua.ObjectIds.ObjectsFolder),
        FILE_DIRECTORY_TYPE,
        "Samples",
        reference_type=ua.ObjectIds.Organizes,
        path="Samples",
    )
    rig.samples = await FileDirectoryBinding.create(app, samples_node, FileStore(samples), samples=SAMPLES)

    async def close() -> None:
        await rig.samples.close()
        await rig.binding.close()

    return close


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def server(tmp_path_factory):
    base = tmp_path_factory.mktemp("fd")
    programs = base / "programs"
    _write_baseline(programs)
    rig = Rig()
    rig.clients = []
    app = await start_app(fast_config(base / "data"), [lambda a: _binder(a, rig, programs, base / "samples")])
    rig.app = app
    try:
        yield rig
    finally:
        await app.stop()


@pytest_asyncio.fixture(loop_scope="module")
async def r(server: Rig):
    """The module's rig; afterwards: sessions closed, roles and protection reset, baseline restored."""
    yield server
    for client in server.clients:
        try:
            await asyncio.wait_for(client.disconnect(), 10)
        except Exception:
            pass  # dropped on purpose by the test
    server.clients.clear()
    manager = server.app.server.iserver.user_manager
    manager.policy = dataclasses.replace(manager.policy, anonymous_role=Role.OPERATOR)
    store = server.store
    store.protect = None
    for entry in store.entries():
        if "/" not in entry.relpath:
            store.delete(entry.relpath)
    for relpath, content in BASELINE.items():
        folder, _, name = relpath.rpartition("/")
        if folder and not any(e.relpath == folder for e in store.entries()):
            store.create_directory("", folder)
        _, handle = store.create_file("setup", folder, name, True)
        assert handle is not None  # asked to open it
        store.write("setup", handle, content)
        store.close("setup", handle)
    server.binding.refresh()
    await server.app.settle()


# ---------------------------------------------------------------------- helpers


def v(value, vtype: ua.VariantType) -> ua.Variant:
    return ua.Variant(value, vtype)


def handle_v(handle: int) -> ua.Variant:
    return v(handle, ua.VariantType.UInt32)


async def call(client: Client, obj: ua.NodeId, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    return await raw_call(client, obj, ua.NodeId(f"{obj.Identifier}.{method}", obj.NamespaceIndex), *args)


async def ok(client: Client, obj: ua.NodeId, method: str, *args: ua.Variant) -> list[Any]:
    res = await call(client, obj, method, *args)
    assert res.StatusCode.is_good(), f"{method}: {res.StatusCode}"
    return [o.Value for o in res.OutputArguments]


def code(res: ua.CallMethodResult) -> int:
    return res.StatusCode.value


def arg_codes(res: ua.CallMethodResult) -> list[int]:
    return [c.value for c in res.InputArgumentResults]


async def value(client: Client, node: ua.NodeId, child: str):
    return await client.get_node(ua.NodeId(f"{node.Identifier}.{child}", node.NamespaceIndex)).read_value()


async def organized(client: Client, node: ua.NodeId) -> dict[str, ua.NodeId]:
    """BrowseName -> TypeDefinition of what ``node`` organizes, as a client browses it."""
    refs = await client.get_node(node).get_references(ua.ObjectIds.Organizes, ua.BrowseDirection.Forward)
    return {ref.BrowseName.Name: ref.TypeDefinition for ref in refs}


async def exists(client: Client, node: ua.NodeId) -> bool:
    dv = await client.get_node(node).read_attribute(ua.AttributeIds.BrowseName, raise_on_bad_status=False)
    return dv.StatusCode.is_good()


async def open_file(client: Client, node: ua.NodeId, mode: int) -> int:
    (handle,) = await ok(client, node, "Open", v(mode, ua.VariantType.Byte))
    return handle


async def read_all(client: Client, node: ua.NodeId) -> bytes:
    handle = await open_file(client, node, R)
    data = b""
    while chunk := (await ok(client, node, "Read", handle_v(handle), v(4096, ua.VariantType.Int32)))[0]:
        data += chunk
    await ok(client, node, "Close", handle_v(handle))
    return data


async def drop(client: Client) -> None:
    """Lose the connection without CloseSession, as a crashed client or a pulled cable would."""
    for task in (client._stale_watchdog_task, client._supervisor_task, client._renew_channel_task):
        await Client._cancel_task(task)
    client.disconnect_socket()


# ---------------------------------------------------------------------- the tree


async def test_existing_entries_become_nodes_when_bound(r: Rig):
    ft, fdt = FILE_TYPE, FILE_DIRECTORY_TYPE
    assert r.initial == {"pick.robot": ft, "lib": fdt}
    c = await r.connect(Role.OPERATOR)
    assert await organized(c, ua.NodeId(PROGRAMS, r.ns)) == {"pick.robot": ft, "lib": fdt}
    assert await organized(c, r.node("lib")) == {"gripper.robot": ft}
    pick = r.node("pick.robot")
    name = await c.get_node(pick).read_browse_name()
    assert name == ua.QualifiedName("pick.robot", r.ns)
    assert (await c.get_node(pick).read_display_name()).Text == "pick.robot"
    assert await value(c, pick, "Size") == len(BASELINE["pick.robot"])
    assert await value(c, r.node("lib/gripper.robot"), "Size") == len(BASELINE["lib/gripper.robot"])
    assert await value(c, pick, "Writable") is True
    assert await value(c, pick, "OpenCount") == 0
    assert await value(c, pick, "MaxByteStringLength") == r.store.max_read
    assert await read_all(c, pick) == BASELINE["pick.robot"]


async def test_samples_are_installed_in_an_empty_directory(r: Rig):
    root = r.samples.store.root
    assert {p.name: p.read_bytes() for p in root.iterdir()} == SAMPLES
    c = await r.connect(Role.OPERATOR)
    assert await organized(c, r.samples.node) == {"a.robot": FILE_TYPE, "b.robot": FILE_TYPE}
    assert await value(c, r.samples.node_of("b.robot"), "Size") == len(SAMPLES["b.robot"])


async def test_node_ids_follow_the_path_and_resolve_back(r: Rig):
    pick = r.node("pick.robot")
    assert pick == ua.NodeId(f"{PROGRAMS}/pick.robot/", r.ns)
    assert r.binding.relpath_of(pick) == "pick.robot"
    assert r.binding.relpath_of(r.node("lib/gripper.robot")) == "lib/gripper.robot"
    assert r.binding.node_of("") == ua.NodeId(PROGRAMS, r.ns)
    not_files = [
        r.node("lib"),  # a directory
        ua.NodeId(PROGRAMS, r.ns),
        ua.NodeId(f"{PROGRAMS}/pick.robot/.Size", r.ns),  # a member
        r.node("missing.robot"),
        r.samples.node_of("a.robot"),  # a file of another directory
        ua.NodeId(ua.ObjectIds.Server),
    ]
    for node in not_files:
        assert r.binding.relpath_of(node) is None, node
    assert r.samples.relpath_of(r.samples.node_of("a.robot")) == "a.robot"


async def test_entries_changed_outside_opc_ua_appear_and_disappear(r: Rig):
    c = await r.connect(Role.OPERATOR)
    r.store.create_file("local", "lib", "extra.robot", False)
    await r.app.settle()
    assert "extra.robot" in await organized(c, r.node("lib"))
    r.store.delete("lib")
    await r.app.settle()
    assert "lib" not in await organized(c, ua.NodeId(PROGRAMS, r.ns))
    assert not await exists(c, r.node("lib/extra.robot"))
    assert not await exists(c, ua.NodeId(f"{PROGRAMS}/lib/gripper.robot/.Size", r.ns))
    assert r.binding.relpath_of(r.node("lib/gripper.robot")) is None


# ---------------------------------------------------------------------- FileType


async def test_create_file_open_write_close_commits_content_and_size(r: Rig):
    c = await r.connect()
    programs = ua.NodeId(PROGRAMS, r.ns)
    node, handle = await ok(
        c, programs, "CreateFile", v("new.robot", ua.VariantType.String), v(True, ua.VariantType.Boolean)
    )
    assert node == r.node("new.robot") and handle != 0
    # the node is there when the call returns
    assert await organized(c, programs) == {"pick.robot": FILE_TYPE, "lib": FILE_DIRECTORY_TYPE, "new.robot": FILE_TYPE}
    assert await value(c, node, "OpenCount") == 1
    content = b"program New\nmove 0 0 0\n"
    await ok(c, node, "Write", handle_v(handle), v(content[:10], ua.VariantType.ByteString))
    await ok(c, node, "Write", handle_v(handle), v(content[10:], ua.VariantType.ByteString))
    assert (await ok(c, node, "GetPosition", handle_v(handle))) == [len(content)]
    assert (r.store.root / "new.robot").read_bytes() == b""  # nothing before Close
    assert await value(c, node, "Size") == 0
    await ok(c, node, "Close", handle_v(handle))
    assert (r.store.root / "new.robot").read_bytes() == content
    assert await value(c, node, "Size") == len(content)
    assert await value(c, node, "OpenCount") == 0
    assert r.binding.relpath_of(node) == "new.robot"


async def test_create_file_without_open_returns_handle_zero(r: Rig):
    c = await r.connect()
    res = await call(
        c,
        ua.NodeId(PROGRAMS, r.ns),
        "CreateFile",
        v("empty.robot", ua.VariantType.String),
        v(False, ua.VariantType.Boolean),
    )
    assert res.StatusCode.is_good()
    assert res.OutputArguments[0].VariantType == ua.VariantType.NodeId
    assert res.OutputArguments[1].Value == 0 and res.OutputArguments[1].VariantType == ua.VariantType.UInt32
    assert await value(c, r.node("empty.robot"), "OpenCount") == 0


async def test_open_for_reading_read_and_positions(r: Rig):
    c = await r.connect(Role.OPERATOR)
    pick, content = r.node("pick.robot"), BASELINE["pick.robot"]
    handle = await open_file(c, pick, R)
    assert await value(c, pick, "OpenCount") == 1
    res = await call(c, pick, "Read", handle_v(handle), v(7, ua.VariantType.Int32))
    assert res.OutputArguments[0].VariantType == ua.VariantType.ByteString
    assert res.OutputArguments[0].Value == content[:7]
    res = await call(c, pick, "GetPosition", handle_v(handle))
    assert res.OutputArguments[0].Value == 7 and res.OutputArguments[0].VariantType == ua.VariantType.UInt64
    await ok(c, pick, "SetPosition", handle_v(handle), v(2, ua.VariantType.UInt64))
    assert await ok(c, pick, "Read", handle_v(handle), v(1000, ua.VariantType.Int32)) == [content[2:]]
    assert await ok(c, pick, "Read", handle_v(handle), v(10, ua.VariantType.Int32)) == [b""]
    await ok(c, pick, "SetPosition", handle_v(handle), v(10_000, ua.VariantType.UInt64))
    assert await ok(c, pick, "GetPosition", handle_v(handle)) == [len(content)]
    await ok(c, pick, "Close", handle_v(handle))
    assert await value(c, pick, "OpenCount") == 0


@pytest.mark.parametrize("how", ["disconnect", "connection lost"])
async def test_a_client_that_goes_away_without_close_leaves_the_old_content(r: Rig, how: str):
    pick, old = r.node("pick.robot"), BASELINE["pick.robot"]
    writer = await r.connect()
    handle = await open_file(writer, pick, W | E)
    await ok(writer, pick, "Write", handle_v(handle), v(b"half a prog", ua.VariantType.ByteString))
    assert r.store.open_count("pick.robot") == 1
    if how == "disconnect":
        await writer.disconnect()
    else:
        await drop(writer)
    for _ in range(100):  # the server notices a lost connection asynchronously
        if r.store.open_count("pick.robot") == 0:
            break
        await asyncio.sleep(0.05)
    await r.app.settle()
    assert (r.store.root / "pick.robot").read_bytes() == old
    assert not [p for p in r.store.root.iterdir() if p.name.startswith(TEMP_PREFIX)]
    other = await r.connect()
    assert await value(other, pick, "OpenCount") == 0
    assert await value(other, pick, "Size") == len(old)
    handle = await open_file(other, pick, W)  # no longer held by the gone session
    await ok(other, pick, "Close", handle_v(handle))


async def test_two_sessions_have_their_own_handles(r: Rig):
    pick = r.node("pick.robot")
    a, b = await r.connect(), await r.connect()
    ha = await open_file(a, pick, W | E)
    assert code(await call(b, pick, "Open", v(W, ua.VariantType.Byte))) == Code.BadNotWritable
    assert code(await call(b, pick, "Open", v(R, ua.VariantType.Byte))) == Code.BadNotReadable
    for method, args in (("Close", ()), ("GetPosition", ()), ("Write", (v(b"x", ua.VariantType.ByteString),))):
        res = await call(b, pick, method, handle_v(ha), *args)
        assert code(res) == Code.BadInvalidArgument, method
        assert arg_codes(res)[0] == Code.BadInvalidArgument
    assert await value(b, pick, "OpenCount") == 1
    await ok(a, pick, "Write", handle_v(ha), v(b"program Two\n", ua.VariantType.ByteString))
    await ok(a, pick, "Close", handle_v(ha))
    assert await read_all(b, pick) == b"program Two\n"
    # two readers at once
    h1, h2 = await open_file(a, pick, R), await open_file(b, pick, R)
    assert await value(a, pick, "OpenCount") == 2
    await ok(a, pick, "Close", handle_v(h1))
    await ok(b, pick, "Close", handle_v(h2))


async def test_a_handle_belongs_to_the_file_it_was_opened_on(r: Rig):
    c = await r.connect()
    handle = await open_file(c, r.node("pick.robot"), R)
    res = await call(c, r.node("lib/gripper.robot"), "Read", handle_v(handle), v(10, ua.VariantType.Int32))
    assert code(res) == Code.BadInvalidArgument and arg_codes(res) == [Code.BadInvalidArgument, Code.Good]
    await ok(c, r.node("pick.robot"), "Close", handle_v(handle))
    res = await call(c, r.node("pick.robot"), "Close", handle_v(handle))
    assert code(res) == Code.BadInvalidArgument


# ---------------------------------------------------------------------- FileDirectoryType


async def test_delete_file_and_directory(r: Rig):
    c = await r.connect()
    programs = ua.NodeId(PROGRAMS, r.ns)
    pick = r.node("pick.robot")
    assert await ok(c, programs, "Delete", v(pick, ua.VariantType.NodeId)) == []
    assert not (r.store.root / "pick.robot").exists()
    assert not await exists(c, pick)
    assert "pick.robot" not in await organized(c, programs)
    res = await call(c, pick, "Open", v(R, ua.VariantType.Byte))
    assert code(res) == Code.BadNodeIdUnknown  # its methods went with it
    await ok(c, programs, "Delete", v(r.node("lib"), ua.VariantType.NodeId))
    assert not (r.store.root / "lib").exists()
    assert await organized(c, programs) == {}
    assert not await exists(c, r.node("lib/gripper.robot"))


async def test_delete_refuses_what_this_directory_does_not_organize(r: Rig):
    c = await r.connect()
    programs = ua.NodeId(PROGRAMS, r.ns)
    for target in (r.node("lib/gripper.robot"), r.node("nothing.robot"), r.samples.node_of("a.robot"), programs):
        res = await call(c, programs, "Delete", v(target, ua.VariantType.NodeId))
        assert code(res) == Code.BadNotFound, target
        assert arg_codes(res) == [Code.BadNotFound]
    assert (r.store.root / "lib" / "gripper.robot").exists()


async def test_move_or_copy(r: Rig):
    c = await r.connect()
    programs, lib, pick = ua.NodeId(PROGRAMS, r.ns), r.node("lib"), r.node("pick.robot")
    content = BASELINE["pick.robot"]
    # copy into lib
    args = (v(pick, ua.VariantType.NodeId), v(lib, ua.VariantType.NodeId), v(True, ua.VariantType.Boolean))
    (new,) = await ok(c, programs, "MoveOrCopy", *args, v("", ua.VariantType.String))
    assert new == r.node("lib/pick.robot")
    assert await read_all(c, new) == content and await read_all(c, pick) == content
    # rename in place
    args = (v(pick, ua.VariantType.NodeId), v(programs, ua.VariantType.NodeId), v(False, ua.VariantType.Boolean))
    (renamed,) = await ok(c, programs, "MoveOrCopy", *args, v("renamed.robot", ua.VariantType.String))
    assert renamed == r.node("renamed.robot")
    assert not await exists(c, pick) and not (r.store.root / "pick.robot").exists()
    assert await read_all(c, renamed) == content
    assert r.binding.relpath_of(pick) is None and r.binding.relpath_of(renamed) == "renamed.robot"
    # move out of lib: it is lib's MoveOrCopy that organizes the source
    gripper = r.node("lib/gripper.robot")
    args = (v(gripper, ua.VariantType.NodeId), v(programs, ua.VariantType.NodeId), v(False, ua.VariantType.Boolean))
    (moved,) = await ok(c, lib, "MoveOrCopy", *args, v(None, ua.VariantType.String))
    assert moved == r.node("gripper.robot")
    assert await organized(c, lib) == {"pick.robot": FILE_TYPE}
    assert await read_all(c, moved) == BASELINE["lib/gripper.robot"]
    # a directory moves with what it holds
    args = (v(lib, ua.VariantType.NodeId), v(programs, ua.VariantType.NodeId), v(False, ua.VariantType.Boolean))
    (lib2,) = await ok(c, programs, "MoveOrCopy", *args, v("lib2", ua.VariantType.String))
    assert await organized(c, lib2) == {"pick.robot": FILE_TYPE}
    assert await read_all(c, r.node("lib2/pick.robot")) == content
    assert not await exists(c, r.node("lib/pick.robot"))


async def test_move_or_copy_refusals(r: Rig):
    c = await r.connect()
    programs, lib, pick = ua.NodeId(PROGRAMS, r.ns), r.node("lib"), r.node("pick.robot")
    copy = v(True, ua.VariantType.Boolean)
    res = await call(
        c,
        programs,
        "MoveOrCopy",
        v(pick, ua.VariantType.NodeId),
        v(programs, ua.VariantType.NodeId),
        copy,
        v("lib", ua.VariantType.String),
    )
    assert code(res) == Code.BadBrowseNameDuplicated
    assert arg_codes(res) == [Code.Good, Code.Good, Code.Good, Code.BadBrowseNameDuplicated]
    res = await call(
        c,
        programs,
        "MoveOrCopy",
        v(pick, ua.VariantType.NodeId),
        v(r.node("lib/gripper.robot"), ua.VariantType.NodeId),
        copy,
        v("", ua.VariantType.String),
    )
    assert code(res) == Code.BadNotFound and arg_codes(res)[1] == Code.BadNotFound  # target is a file
    res = await call(
        c,
        lib,
        "MoveOrCopy",
        v(pick, ua.VariantType.NodeId),
        v(lib, ua.VariantType.NodeId),
        copy,
        v("", ua.VariantType.String),
    )
    assert code(res) == Code.BadNotFound and arg_codes(res)[0] == Code.BadNotFound  # not organized by lib
    res = await call(
        c,
        programs,
        "MoveOrCopy",
        v(lib, ua.VariantType.NodeId),
        v(lib, ua.VariantType.NodeId),
        v(False, ua.VariantType.Boolean),
        v("", ua.VariantType.String),
    )
    assert code(res) == Code.BadInvalidArgument  # into itself
    assert sorted(p.name for p in r.store.root.iterdir()) == ["lib", "pick.robot"]


async def test_create_directory_then_a_file_inside(r: Rig):
    c = await r.connect()
    programs = ua.NodeId(PROGRAMS, r.ns)
    res = await call(c, programs, "CreateDirectory", v("cell2", ua.VariantType.String))
    assert res.StatusCode.is_good()
    cell2 = res.OutputArguments[0].Value
    assert cell2 == r.node("cell2") and res.OutputArguments[0].VariantType == ua.VariantType.NodeId
    assert (await organized(c, programs))["cell2"] == FILE_DIRECTORY_TYPE
    assert (r.store.root / "cell2").is_dir()
    node, handle = await ok(
        c, cell2, "CreateFile", v("x.robot", ua.VariantType.String), v(True, ua.VariantType.Boolean)
    )
    assert node == r.node("cell2/x.robot")
    await ok(c, node, "Write", handle_v(handle), v(b"program X\n", ua.VariantType.ByteString))
    await ok(c, node, "Close", handle_v(handle))
    assert (r.store.root / "cell2" / "x.robot").read_bytes() == b"program X\n"
    assert await organized(c, cell2) == {"x.robot": FILE_TYPE}
    assert r.binding.relpath_of(node) == "cell2/x.robot"
    assert r.binding.relpath_of(cell2) is None


async def test_refusals_arrive_as_call_results(r: Rig):
    c = await r.connect()
    programs, pick = ua.NodeId(PROGRAMS, r.ns), r.node("pick.robot")
    no = v(False, ua.VariantType.Boolean)
    for name in ("pick.robot", "lib"):
        res = await call(c, programs, "CreateFile", v(name, ua.VariantType.String), no)
        assert code(res) == Code.BadBrowseNameDuplicated
        assert arg_codes(res) == [Code.BadBrowseNameDuplicated, Code.Good]
    res = await call(c, programs, "CreateDirectory", v("lib", ua.VariantType.String))
    assert code(res) == Code.BadBrowseNameDuplicated
    for bad in ("a/b", "..", ""):
        res = await call(c, programs, "CreateFile", v(bad, ua.VariantType.String), no)
        assert code(res) == Code.BadInvalidArgument, bad
        assert arg_codes(res) == [Code.BadBrowseNameInvalid, Code.Good]
    res = await call(c, pick, "Open", v(0, ua.VariantType.Byte))
    assert code(res) == Code.BadInvalidArgument and arg_codes(res) == [Code.BadInvalidArgument]
    handle = await open_file(c, pick, R)
    res = await call(c, pick, "Read", handle_v(handle), v(0, ua.VariantType.Int32))
    assert code(res) == Code.BadInvalidArgument and arg_codes(res) == [Code.Good, Code.BadInvalidArgument]
    res = await call(c, pick, "Write", handle_v(handle), v(b"x", ua.VariantType.ByteString))
    assert code(res) == Code.BadInvalidState  # opened for reading
    res = await call(c, pick, "Read", handle_v(handle + 1000), v(5, ua.VariantType.Int32))
    assert code(res) == Code.BadInvalidArgument and arg_codes(res) == [Code.BadInvalidArgument, Code.Good]
    res = await call(c, pick, "Read", v(handle, ua.VariantType.Int32), v(5, ua.VariantType.Int32))
    assert code(res) == Code.BadTypeMismatch  # the dispatcher checks types before the store sees them
    # open files cannot be deleted or moved
    res = await call(c, programs, "Delete", v(pick, ua.VariantType.NodeId))
    assert code(res) == Code.BadInvalidState
    await ok(c, pick, "Close", handle_v(handle))
    assert sorted(p.name for p in r.store.root.iterdir()) == ["lib", "pick.robot"]


async def test_a_protection_change_republishes_writable_without_asking_the_disk(r: Rig, monkeypatch):
    """A program loaded or unloaded changes only what the store's ``protect`` says: Writable and
    UserWritable follow from the entry published last, no entry is read again."""
    c = await r.connect()
    pick = r.node("pick.robot")
    asked: list[str] = []
    entry = r.store.entry

    def asked_entry(relpath: str) -> Entry:
        asked.append(relpath)
        return entry(relpath)

    monkeypatch.setattr(r.store, "entry", asked_entry)
    r.store.protect = lambda relpath: relpath == "pick.robot"
    r.binding.protection_changed("pick.robot")
    await r.app.settle()
    assert (await value(c, pick, "Writable"), await value(c, pick, "UserWritable")) == (False, False)
    r.store.protect = None
    r.binding.protection_changed("pick.robot")
    await r.app.settle()
    assert (await value(c, pick, "Writable"), await value(c, pick, "UserWritable")) == (True, True)
    assert await value(c, pick, "Size") == len(BASELINE["pick.robot"])
    assert asked == []


async def test_protected_entry_answers_bad_invalid_state(r: Rig):
    c = await r.connect()
    programs, pick = ua.NodeId(PROGRAMS, r.ns), r.node("pick.robot")
    r.store.protect = lambda relpath: relpath == "pick.robot"
    r.binding.refresh()
    await r.app.settle()
    assert await value(c, pick, "Writable") is False
    assert await value(c, pick, "UserWritable") is False
    assert code(await call(c, pick, "Open", v(W, ua.VariantType.Byte))) == Code.BadInvalidState
    assert code(await call(c, programs, "Delete", v(pick, ua.VariantType.NodeId))) == Code.BadInvalidState
    move = (v(pick, ua.VariantType.NodeId), v(r.node("lib"), ua.VariantType.NodeId))
    res = await call(c, programs, "MoveOrCopy", *move, v(False, ua.VariantType.Boolean), v("", ua.VariantType.String))
    assert code(res) == Code.BadInvalidState
    await ok(c, programs, "MoveOrCopy", *move, v(True, ua.VariantType.Boolean), v("", ua.VariantType.String))
    assert await read_all(c, pick) == BASELINE["pick.robot"]  # reading is fine
    # protected after Open: Write refuses, and Close discards
    r.store.protect = None
    handle = await open_file(c, pick, W | E)
    r.store.protect = lambda relpath: relpath == "pick.robot"
    res = await call(c, pick, "Write", handle_v(handle), v(b"x", ua.VariantType.ByteString))
    assert code(res) == Code.BadNotWritable
    assert code(await call(c, pick, "Close", handle_v(handle))) == Code.BadInvalidState
    assert (r.store.root / "pick.robot").read_bytes() == BASELINE["pick.robot"]
    assert await value(c, pick, "OpenCount") == 0


# ---------------------------------------------------------------------- roles


async def test_observer_may_neither_write_nor_create(r: Rig):
    c = await r.connect(Role.OBSERVER)
    programs, pick = ua.NodeId(PROGRAMS, r.ns), r.node("pick.robot")
    for mode in (W, R | W, W | E):
        res = await call(c, pick, "Open", v(mode, ua.VariantType.Byte))
        assert code(res) == Code.BadUserAccessDenied, mode
    res = await call(c, programs, "CreateFile", v("x.robot", ua.VariantType.String), v(True, ua.VariantType.Boolean))
    assert code(res) == Code.BadUserAccessDenied
    assert code(await call(c, programs, "Delete", v(pick, ua.VariantType.NodeId))) == Code.BadUserAccessDenied
    assert await value(c, pick, "UserWritable") is False
    assert r.store.open_count("pick.robot") == 0
    assert sorted(p.name for p in r.store.root.iterdir()) == ["lib", "pick.robot"]


async def test_operator_reads_but_engineer_writes(r: Rig):
    operator = await r.connect(Role.OPERATOR)
    engineer = await r.connect(Role.ENGINEER)
    programs, pick = ua.NodeId(PROGRAMS, r.ns), r.node("pick.robot")
    assert await read_all(operator, pick) == BASELINE["pick.robot"]
    assert code(await call(operator, pick, "Open", v(R | W, ua.VariantType.Byte))) == Code.BadUserAccessDenied
    res = await call(
        operator, programs, "CreateFile", v("x.robot", ua.VariantType.String), v(False, ua.VariantType.Boolean)
    )
    assert code(res) == Code.BadUserAccessDenied
    assert (
        code(await call(operator, programs, "CreateDirectory", v("d", ua.VariantType.String)))
        == Code.BadUserAccessDenied
    )
    assert not (r.store.root / "x.robot").exists() and not (r.store.root / "d").exists()
    # UserWritable is per session; Writable is the same for everyone
    assert await value(operator, pick, "Writable") is True
    assert await value(operator, pick, "UserWritable") is False
    assert await value(engineer, pick, "UserWritable") is True
    await ok(engineer, programs, "CreateFile", v("x.robot", ua.VariantType.String), v(False, ua.VariantType.Boolean))
    assert (r.store.root / "x.robot").exists()


async def test_session_closed_drops_only_that_sessions_handles(r: Rig):
    a, b = await r.connect(), await r.connect()
    pick = r.node("pick.robot")
    await open_file(a, pick, R)
    hb = await open_file(b, pick, R)
    assert await value(b, pick, "OpenCount") == 2
    await a.disconnect()
    r.clients.remove(a)
    await r.app.settle()
    assert await value(b, pick, "OpenCount") == 1
    assert await ok(b, pick, "Read", handle_v(hb), v(7, ua.VariantType.Int32)) == [BASELINE["pick.robot"][:7]]
