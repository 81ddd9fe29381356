"""OPC 40001-1 Machinery through a real asyncua client over TCP, as a client that knows only OPC 40001-1
finds it: ``Objects/Machines`` by the Machinery namespace URI, each machine's Identification, its
MachineryItemState and MachineryOperationMode following a PackML cycle and a robot program run, with
their TransitionEvents. One server serves the module (the demo cell with ``[[machines]]`` entries)."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import Collector, call_path, raw_call

from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.core.errors import ConfigError
from uacell.robotics.binding import CONTROLLERS
from uacell.server import UacellServer

module_loop = pytest.mark.asyncio(loop_scope="module")
pytestmark = module_loop

MACHINERY = "http://opcfoundation.org/UA/Machinery/"
DI = "http://opcfoundation.org/UA/DI/"
CELL = "urn:uacell:cell"
TIMEOUT = 20.0
EXEC = "Filler1.BaseStateMachine.MachineState.ExecuteState"
MACH = "Filler1.BaseStateMachine.MachineState"
BASE = "Filler1.BaseStateMachine"
CTRL = "Robot1.Controllers.Controller1"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
TC = f"{CTRL}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
SHORT = "program Short version 1\nmove 10 0 0 0 0 0\nwait 2\nmove 0 0 0 0 0 0\n"

MACHINES = """
[machinery]
location = "Plant 1/Hall 3"

[[machines]]
name = "Filler1"
manufacturer = "ACME Packaging"
model = "F-400"
serial_number = "F-2291"
product_instance_uri = "urn:acme:filler:F-2291"
year_of_construction = 2021
month_of_construction = 5
initial_operation_date = "2021-09-01"

[[machines]]
name = "Robot1"
year_of_construction = 2019
location = "Hall 3/Cell 2"
"""


class Rig:
    app: UacellServer
    client: Client
    m: int  # the Machinery namespace's index, found by URI
    di: int
    machines: dict[str, ua.NodeId]


def config_with_machines(data_dir: Path, extra: str = MACHINES) -> Any:
    config = fast_config(data_dir / "data")
    config.server.anonymous_role = "engineer"  # uploads a robot program
    path = data_dir / "cell.toml"
    path.write_text(builtin_cell_path("demo").read_text() + extra)
    config.cell = load_cell(path)
    config.sections["machinery"].location = "Plant 1/Hall 3"  # what [machinery] in a settings file sets
    return config


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def rig(tmp_path_factory):
    app = await start_app(config_with_machines(tmp_path_factory.mktemp("machinery")))
    client = Client(app.endpoint, timeout=30)
    await client.connect()
    r = Rig()
    r.app, r.client = app, client
    r.m = await client.get_namespace_index(MACHINERY)
    r.di = await client.get_namespace_index(DI)
    try:
        folder = await machines_folder(r)
        refs = await folder.get_references(ua.ObjectIds.Organizes, ua.BrowseDirection.Forward)
        r.machines = {ref.BrowseName.Name: ref.NodeId for ref in refs}
        yield r
    finally:
        await client.disconnect()
        await app.stop()


async def machines_folder(r: Rig) -> Any:
    """``Machines`` found as a generic client finds it: browsed from Objects by its BrowseName."""
    objects = r.client.nodes.objects
    for ref in await objects.get_references(ua.ObjectIds.Organizes, ua.BrowseDirection.Forward):
        if ref.BrowseName == ua.QualifiedName("Machines", r.m):
            return r.client.get_node(ref.NodeId)
    raise AssertionError("no Machines folder in Objects")


async def child(r: Rig, node: ua.NodeId, *path: str) -> Any:
    return await r.client.get_node(node).get_child(list(path))


def block(r: Rig, name: str) -> list[str]:
    return [f"{r.m}:MachineryBuildingBlocks", f"{r.m}:{name}"]


async def current(r: Rig, machine: str, name: str) -> tuple[str, int]:
    sm = await child(r, r.machines[machine], *block(r, name))
    text = (await (await sm.get_child("0:CurrentState")).read_value()).Text
    number = await (await sm.get_child(["0:CurrentState", "0:Number"])).read_value()
    return text, number


async def until(r: Rig, machine: str, name: str, wanted: str) -> None:
    async with asyncio.timeout(TIMEOUT):
        while (await current(r, machine, name))[0] != wanted:
            await asyncio.sleep(0.02)


async def identification(r: Rig, machine: str) -> dict[str, Any]:
    ident = await child(r, r.machines[machine], f"{r.di}:Identification")
    out = {}
    for prop in await ident.get_children(refs=ua.ObjectIds.HasProperty):
        value = await prop.read_value()
        out[(await prop.read_browse_name()).Name] = value.Text if isinstance(value, ua.LocalizedText) else value
    return out


async def ok(client: Client, obj: str, method: str, *args: ua.Variant) -> None:
    res = await call_path(client, obj, method, *args)
    assert res.StatusCode.is_good(), (obj, method, res.StatusCode)


async def subscribe(r: Rig, *nodes: ua.NodeId) -> tuple[Collector, Any]:
    events = Collector()
    events.timeout = TIMEOUT
    sub = await r.client.create_subscription(20, events)
    evtype = r.client.get_node(ua.ObjectIds.TransitionEventType)
    for node in nodes:
        await sub.subscribe_events(r.client.get_node(node), evtype)
    return events, sub


def to_states(events: Collector, source: ua.NodeId) -> list[str]:
    return [e.ToState.Text for e in events.events if getattr(e, "SourceNode", None) == source]


# --- finding the machines ---------------------------------------------------------------------------


async def test_machines_organizes_every_robot_and_unit_with_the_building_blocks(rig):
    r = rig
    cell = await r.client.get_namespace_index(CELL)
    assert r.machines == {"Robot1": ua.NodeId("Robot1", cell), "Filler1": ua.NodeId("Filler1", cell)}
    for name, node in r.machines.items():
        machine = r.client.get_node(node)
        add_ins = {
            ref.BrowseName.to_string(): ref.TypeDefinition
            for ref in await machine.get_references(ua.ObjectIds.HasAddIn, ua.BrowseDirection.Forward)
        }
        # MachineIdentificationType; a robot's Components (MachineComponentsType) too
        components = {f"{r.m}:Components": ua.NodeId(1006, r.m)} if name == "Robot1" else {}
        assert add_ins == {f"{r.di}:Identification": ua.NodeId(1012, r.m), **components}, name
        blocks = await machine.get_child(f"{r.m}:MachineryBuildingBlocks")
        assert await blocks.read_type_definition() == ua.NodeId(ua.ObjectIds.FolderType)
        in_blocks = {
            ref.BrowseName.to_string(): ref.TypeDefinition
            for ref in await blocks.get_references(ua.ObjectIds.HasAddIn, ua.BrowseDirection.Forward)
        }
        assert in_blocks == {
            f"{r.di}:Identification": ua.NodeId(1012, r.m),
            f"{r.m}:MachineryItemState": ua.NodeId(1002, r.m),  # MachineryItemState_StateMachineType
            f"{r.m}:MachineryOperationMode": ua.NodeId(1008, r.m),  # MachineryOperationModeStateMachineType
            **components,
        }


async def test_a_robots_components_are_its_controllers_and_motion_devices_with_their_identification(rig):
    r = rig
    components = await child(r, r.machines["Robot1"], f"{r.m}:Components")
    found = {
        ref.BrowseName.Name: ref.NodeId
        for ref in await components.get_references(ua.ObjectIds.HasComponent, ua.BrowseDirection.Forward)
    }
    cell = await r.client.get_namespace_index(CELL)
    assert found == {"Controller1": ua.NodeId(CTRL, cell), "Arm1": ua.NodeId("Robot1.MotionDevices.Arm1", cell)}
    ident = await r.client.get_node(found["Controller1"]).get_child(f"{r.di}:Identification")
    assert await ident.read_type_definition() == ua.NodeId(1005, r.m)  # MachineryComponentIdentificationType
    r.machines["Controller1"] = found["Controller1"]
    # the controller's DI identification (the demo cell's), now also where a Machinery client looks
    assert await identification(r, "Controller1") == {
        "Manufacturer": "uacell",
        "Model": "Simulated controller",
        "ProductCode": "SIM-C",
        "SerialNumber": "DEMO-C1",
    }
    del r.machines["Controller1"]


async def test_identification_from_the_cell_file(rig):
    r = rig
    application_uri = r.app.config.server.application_uri
    assert await identification(r, "Filler1") == {
        "Manufacturer": "ACME Packaging",
        "Model": "F-400",
        "SerialNumber": "F-2291",
        "ProductInstanceUri": "urn:acme:filler:F-2291",
        "YearOfConstruction": 2021,
        "MonthOfConstruction": 5,
        "InitialOperationDate": datetime(2021, 9, 1, tzinfo=UTC),
        "Location": "Plant 1/Hall 3",  # [machinery] location
    }
    # the robot's own DI identification, with what its [[machines]] entry adds
    assert await identification(r, "Robot1") == {
        "Manufacturer": "uacell",
        "Model": "Simulated robot system",
        "SerialNumber": "DEMO-R1",
        "ProductInstanceUri": f"{application_uri}:machine:Robot1",
        "YearOfConstruction": 2019,
        "Location": "Hall 3/Cell 2",
    }


async def test_the_state_machines_publish_the_nodesets_ids(rig):
    r = rig
    sm = await child(r, r.machines["Filler1"], *block(r, "MachineryItemState"))
    available = await (await sm.get_child("0:AvailableStates")).read_value()
    assert sorted(a.Identifier for a in available) == [5004, 5005, 5006, 5007]  # the type's state objects
    state_id = await (await sm.get_child(["0:CurrentState", "0:Id"])).read_value()
    text, number = await current(r, "Filler1", "MachineryItemState")
    assert {5004: "OutOfService", 5005: "NotAvailable", 5006: "Executing", 5007: "NotExecuting"}[
        state_id.Identifier
    ] == text
    assert state_id.NamespaceIndex == r.m and number in (0, 1, 2, 3)


# --- following the cell ---------------------------------------------------------------------------


async def test_a_packml_cycle(rig):
    r = rig
    item = await child(r, r.machines["Filler1"], *block(r, "MachineryItemState"))
    mode = await child(r, r.machines["Filler1"], *block(r, "MachineryOperationMode"))
    assert await current(r, "Filler1", "MachineryItemState") == ("NotExecuting", 2)  # Stopped
    assert await current(r, "Filler1", "MachineryOperationMode") == ("Processing", 3)  # Produce
    cell = await r.client.get_namespace_index(CELL)
    events, sub = await subscribe(r, item.nodeid, mode.nodeid)
    try:
        await ok(r.client, MACH, "Reset")
        await wait_path(r, cell, EXEC, "Idle")
        await ok(r.client, EXEC, "Start", ua.Variant([], ua.VariantType.ExtensionObject, is_array=True))
        await until(r, "Filler1", "MachineryItemState", "Executing")
        assert await current(r, "Filler1", "MachineryItemState") == ("Executing", 3)
        await ok(r.client, MACH, "Stop")
        await until(r, "Filler1", "MachineryItemState", "NotExecuting")  # from Stopping on
        await wait_path(r, cell, MACH, "Stopped")
        await ok(r.client, "Filler1", "SetUnitMode", ua.Variant(2, ua.VariantType.Int32))  # Maintenance
        await until(r, "Filler1", "MachineryOperationMode", "Maintenance")
        await ok(r.client, BASE, "Abort")
        await until(r, "Filler1", "MachineryItemState", "OutOfService")  # from Aborting on
        await wait_path(r, cell, BASE, "Aborted")
        assert await current(r, "Filler1", "MachineryItemState") == ("OutOfService", 1)
        await ok(r.client, BASE, "Clear")
        await until(r, "Filler1", "MachineryItemState", "NotExecuting")
        await wait_path(r, cell, MACH, "Stopped")
        await ok(r.client, "Filler1", "SetUnitMode", ua.Variant(3, ua.VariantType.Int32))  # Manual
        await until(r, "Filler1", "MachineryOperationMode", "Setup")
        await ok(r.client, "Filler1", "SetUnitMode", ua.Variant(1, ua.VariantType.Int32))  # Produce
        await until(r, "Filler1", "MachineryOperationMode", "Processing")
        last = await events.wait_for(lambda e: getattr(e, "ToState", None) == ua.LocalizedText("Processing"))
        assert to_states(events, item.nodeid) == ["Executing", "NotExecuting", "OutOfService", "NotExecuting"]
        assert to_states(events, mode.nodeid) == ["Maintenance", "Setup", "Processing"]
        assert last.Transition.Text == "FromSetupToProcessing"
        assert last.SourceNode == mode.nodeid
        # the transition's own NodeSet node (FromSetupToProcessing, ns=Machinery;i=5038)
        transition_id = await (await mode.get_child(["0:LastTransition", "0:Id"])).read_value()
        assert transition_id == ua.NodeId(5038, r.m)
    finally:
        await sub.delete()


async def test_a_robot_program_run(rig):
    r = rig
    cell = await r.client.get_namespace_index(CELL)
    item = await child(r, r.machines["Robot1"], *block(r, "MachineryItemState"))
    assert await current(r, "Robot1", "MachineryItemState") == ("NotExecuting", 2)  # Idle
    assert await current(r, "Robot1", "MachineryOperationMode") == ("Processing", 3)  # the simulator: AUTOMATIC
    await upload(r, cell, "short.robot", SHORT)
    events, sub = await subscribe(r, item.nodeid)
    try:
        await ok(r.client, SO, "GetReady")
        await wait_path(r, cell, SO, "Ready")
        await ok(r.client, TC, "LoadByName", ua.Variant("short", ua.VariantType.String))
        await ok(r.client, TC, "Start")
        await until(r, "Robot1", "MachineryItemState", "Executing")
        await until(r, "Robot1", "MachineryItemState", "NotExecuting")  # the program ended
        await events.wait_for(lambda e: getattr(e, "ToState", None) == ua.LocalizedText("NotExecuting"))
        assert to_states(events, item.nodeid) == ["Executing", "NotExecuting"]
        transitions = [e.Transition.Text for e in events.events]
        assert transitions == ["FromNotExecutingToExecuting", "FromExecutingToNotExecuting"]
    finally:
        await sub.delete()
    await ok(r.client, SO, "StandDown")


async def test_a_robot_alarm_puts_it_out_of_service_until_cleared(rig):
    r = rig
    equipment = r.app.registry(CONTROLLERS)[CTRL].cell.equipment
    name = next(iter(r.app.registry(CONTROLLERS)[CTRL].cell.system.conditions))
    equipment.raise_alarm(name, "test fault")  # the simulated controller's own fault
    await until(r, "Robot1", "MachineryItemState", "OutOfService")
    equipment.clear_alarm(name)
    await until(r, "Robot1", "MachineryItemState", "NotExecuting")  # inactive (acknowledged or not)


async def wait_path(r: Rig, cell: int, path: str, wanted: str) -> None:
    node = r.client.get_node(ua.NodeId(f"{path}.CurrentState", cell))
    async with asyncio.timeout(TIMEOUT):
        while (await node.read_value()).Text != wanted:
            await asyncio.sleep(0.02)


class HasClient(Protocol):
    client: Client


async def upload(r: HasClient, cell: int, name: str, text: str) -> None:
    """CreateFile + Write + Close in the controller's Programs (FileDirectoryType) through OPC UA."""
    programs = ua.NodeId(f"{CTRL}.Programs", cell)
    res = await raw_call(
        r.client,
        programs,
        ua.NodeId(f"{CTRL}.Programs.CreateFile", cell),
        ua.Variant(name, ua.VariantType.String),
        ua.Variant(True, ua.VariantType.Boolean),
    )
    assert res.StatusCode.is_good(), res.StatusCode
    file_id, handle = res.OutputArguments[0].Value, res.OutputArguments[1].Value
    file_node = r.client.get_node(file_id)
    write = (await file_node.get_child("0:Write")).nodeid
    close = (await file_node.get_child("0:Close")).nodeid
    handle_v = ua.Variant(handle, ua.VariantType.UInt32)
    res = await raw_call(r.client, file_id, write, handle_v, ua.Variant(text.encode(), ua.VariantType.ByteString))
    assert res.StatusCode.is_good(), res.StatusCode
    res = await raw_call(r.client, file_id, close, handle_v)
    assert res.StatusCode.is_good(), res.StatusCode


# --- a [[machines]] entry that names no machine ------------------------------------------------------


async def test_an_entry_naming_no_robot_or_unit_stops_the_start(tmp_path):
    config = config_with_machines(tmp_path, '\n[[machines]]\nname = "Filler9"\n')
    app = UacellServer(config)
    try:
        with pytest.raises(ConfigError, match=r"\[machines.Filler9\] name: 'Filler9' is no robot or PackML unit"):
            await app.setup()
    finally:
        await app.stop()


# --- the HMI's view ------------------------------------------------------------------------------------


async def test_the_hmi_finds_one_tile_per_machine_with_its_state_and_mode(rig):
    from uacell.core.companion import web_views
    from uacell.web.discovery import discover

    r = rig
    async with Client(r.app.endpoint, timeout=30) as client:
        cell = await discover(client, web_views(r.app.companions))
        tiles = {m["name"]: m for m in cell.layout["machines"]}
        assert set(tiles) == {"Robot1", "Filler1"}
        filler = tiles["Filler1"]
        assert filler["state"]["key"] == "Machines/Filler1/MachineryItemState"
        # each key leads to the node of that BrowseName path
        state = client.get_node(cell.variables[filler["state"]["state"]])
        mode = client.get_node(cell.variables[filler["mode"]["state"]])
        assert (await state.read_value()).Text == (await current(r, "Filler1", "MachineryItemState"))[0]
        assert (await mode.read_value()).Text == (await current(r, "Filler1", "MachineryOperationMode"))[0]
        serial = client.get_node(cell.variables[filler["identification"]["SerialNumber"]])
        assert await serial.read_value() == "F-2291"
        assert set(tiles["Robot1"]["identification"]) == {
            "Manufacturer",
            "Model",
            "SerialNumber",
            "ProductInstanceUri",
            "YearOfConstruction",
            "Location",
        }
        # their TransitionEvents are listed with the others' (the page's "Last transitions")
        assert (
            cell.machines[state.nodeid.to_string().removesuffix(".CurrentState")]
            == "Machines/Filler1/MachineryItemState"
        )


# --- identification the equipment reports of itself ---------------------------------------------------


def reporting_unit(spec: Any) -> Any:
    """A simulated unit whose equipment reports who made it (``identification``), as a PLC that knows
    its nameplate would: the factory a cell file names as ``test_machinery_server:reporting_unit``."""
    from uacell.packml.sim import simulator

    unit = simulator(spec)
    vars(unit)["identification"] = {
        "Manufacturer": "PLC Maker",
        "SerialNumber": "PLC-77",
        "Model": "",
        "DeviceRevision": "3",
    }
    return unit


async def test_identification_the_equipment_reports_under_the_cell_files(tmp_path):
    from conftest import serving

    path = tmp_path / "cell.toml"
    path.write_text(
        '[[packml_units]]\nname = "Labeler"\nequipment = "test_machinery_server:reporting_unit"\n'
        '[[machines]]\nname = "Labeler"\nmanufacturer = "ACME (as the plant knows it)"\n'
    )
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (app, client):
        r = Rig()
        r.app, r.client = app, client
        r.m = await client.get_namespace_index(MACHINERY)
        r.di = await client.get_namespace_index(DI)
        r.machines = {"Labeler": ua.NodeId("Labeler", await client.get_namespace_index(CELL))}
        assert await identification(r, "Labeler") == {
            "Manufacturer": "ACME (as the plant knows it)",  # the cell file wins
            "SerialNumber": "PLC-77",  # the equipment's, where the file says nothing
            "ProductInstanceUri": f"{app.config.server.application_uri}:machine:Labeler",
        }  # an empty Model and DI's DeviceRevision (no Machinery property) are not taken
