"""OPC 40001-1 Machinery seen by node-opcua, a client that knows nothing of uacell: ``Objects/Machines``
by the Machinery namespace URI, each machine's identification, state and mode through a PackML cycle,
a robot program run and a gateway PLC's communication loss (also read with asyncua, with the
TransitionEvents); and the NodeSet export loaded into node-opcua with the Machinery NodeSet shows the
same machines as the live server."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import NodeServer, fast_config, run_node, serving, start_serve
from helpers import Collector, call_path, free_port, official, until
from helpers import cell_state as state
from test_gateway_packml import PLC, cell
from test_machinery_server import EXEC, MACH, MACHINES, SO, TC, config_with_machines, upload
from test_nodeset_export import differences, run_export
from test_robotics_interop import run_trusted

from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.models.source import locate_models

pytestmark = pytest.mark.interop
MACHINERY = "http://opcfoundation.org/UA/Machinery/"
LONG = "program Long version 1\nmove 10 0 0 0 0 0\nwait 1000\n"  # 50 s real at time_scale 20, or a Stop


async def machines(endpoint: str) -> dict[str, Any]:
    """What node-opcua's machines.js sees (run beside the in-process server's event loop)."""
    out: dict[str, Any] = (await asyncio.to_thread(run_node, "machines.js", endpoint))["machines"]
    return out


async def test_node_opcua_follows_a_packml_cycle_and_a_robot_run(tmp_path: Path) -> None:
    async with serving(config_with_machines(tmp_path)) as (app, client):
        seen = await machines(app.endpoint)
        assert set(seen) == {"Robot1", "Filler1"}
        assert seen["Filler1"]["identification"] == {
            "Manufacturer": "ACME Packaging",
            "Model": "F-400",
            "SerialNumber": "F-2291",
            "ProductInstanceUri": "urn:acme:filler:F-2291",
            "YearOfConstruction": 2021,
            "MonthOfConstruction": 5,
            "InitialOperationDate": "2021-09-01T00:00:00.000Z",
            "Location": "Plant 1/Hall 3",
        }
        assert seen["Robot1"]["identification"]["SerialNumber"] == "DEMO-R1"
        assert seen["Robot1"]["identification"]["YearOfConstruction"] == 2019
        assert {n: (m["itemState"], m["operationMode"]) for n, m in seen.items()} == {
            "Robot1": (["NotExecuting", 2], ["Processing", 3]),
            "Filler1": (["NotExecuting", 2], ["Processing", 3]),
        }
        # the unit produces, the robot runs a program: both Executing
        assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
        await until(lambda: state(client, EXEC), "Idle")
        start = await call_path(client, EXEC, "Start", ua.Variant([], ua.VariantType.ExtensionObject, is_array=True))
        assert start.StatusCode.is_good()
        cell_ns = await client.get_namespace_index("urn:uacell:cell")
        r = _Rig(app, client)
        await upload(r, cell_ns, "long.robot", LONG)
        assert (await call_path(client, SO, "GetReady")).StatusCode.is_good()
        await until(lambda: state(client, SO), "Ready")
        assert (
            await call_path(client, TC, "LoadByName", ua.Variant("long", ua.VariantType.String))
        ).StatusCode.is_good()
        assert (await call_path(client, TC, "Start")).StatusCode.is_good()
        await until(lambda: state(client, EXEC), "Execute")
        await app.settle()
        seen = await machines(app.endpoint)
        assert seen["Filler1"]["itemState"] == ["Executing", 3]
        assert seen["Robot1"]["itemState"] == ["Executing", 3]
        # the unit in Maintenance, stopped; the robot's program stopped
        assert (await call_path(client, MACH, "Stop")).StatusCode.is_good()
        await until(lambda: state(client, MACH), "Stopped")
        assert (
            await call_path(client, "Filler1", "SetUnitMode", ua.Variant(2, ua.VariantType.Int32))
        ).StatusCode.is_good()
        quick_stop = ua.Variant(4, ua.VariantType.Int64)  # StopMode QUICK_STOP
        assert (await call_path(client, TC, "Stop", quick_stop)).StatusCode.is_good()
        await until(lambda: state(client, SO), "Ready")
        await app.settle()
        seen = await machines(app.endpoint)
        assert (seen["Filler1"]["itemState"], seen["Filler1"]["operationMode"]) == (
            ["NotExecuting", 2],
            ["Maintenance", 1],
        )
        assert seen["Robot1"]["itemState"] == ["NotExecuting", 2]


class _Rig:
    """What ``test_machinery_server.upload`` needs of its rig."""

    def __init__(self, app: Any, client: Client) -> None:
        self.app, self.client = app, client


async def test_a_gateway_unit_whose_plc_is_lost_is_not_available(tmp_path: Path) -> None:
    p = PLC(["Capper"])
    p.start()
    try:
        path = tmp_path / "cell.toml"
        path.write_text(cell(p, ["Capper"]) + '\n[[machines]]\nname = "Capper"\nserial_number = "C-7"\n')
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (app, client):
            m = await client.get_namespace_index(MACHINERY)
            cell_ns = await client.get_namespace_index("urn:uacell:cell")
            blocks = client.get_node(ua.NodeId("Capper.MachineryBuildingBlocks", cell_ns))
            item = await blocks.get_child(f"{m}:MachineryItemState")
            mode = await blocks.get_child(f"{m}:MachineryOperationMode")

            async def item_state() -> str:
                return str((await (await item.get_child("0:CurrentState")).read_value()).Text)

            assert await item_state() == "NotExecuting"
            events = Collector()
            sub = await client.create_subscription(20, events)
            await sub.subscribe_events(item, client.get_node(ua.ObjectIds.TransitionEventType))
            p.kill()
            await until(item_state, "NotAvailable", timeout=20.0)
            assert (await (await mode.get_child("0:CurrentState")).read_value()).Text == "None"
            lost = await events.wait_for(lambda e: getattr(e, "ToState", None) == ua.LocalizedText("NotAvailable"))
            assert lost.Transition.Text == "FromNotExecutingToNotAvailable"
            assert lost.SourceNode == item.nodeid
            seen = await machines(app.endpoint)
            assert seen["Capper"]["itemState"] == ["NotAvailable", 0]
            assert seen["Capper"]["operationMode"] == ["None", 0]
            assert seen["Capper"]["identification"]["SerialNumber"] == "C-7"  # uacell's own: readable while lost
            p.start()  # the same port
            await until(item_state, "NotExecuting", timeout=20.0)
            assert (await (await mode.get_child("0:CurrentState")).read_value()).Text == "Processing"
            await sub.delete()
    finally:
        p.kill()


def test_the_export_loaded_into_node_opcua_shows_the_same_machines(tmp_path: Path) -> None:
    config = tmp_path / "cell.toml"
    config.write_text(
        MACHINES.split("\n[[machines]]", 1)[0] + builtin_cell_path("demo").read_text() + MACHINES.split("\n", 3)[3]
    )
    export = run_export(tmp_path, config)
    models = locate_models(official())
    port = free_port()
    files = [str(p) for p in (*(models[m.key] for m in official()), export)]
    assert any(f.endswith("Opc.Ua.Machinery.NodeSet2.xml") for f in files)
    bare = NodeServer("bench_server.js", [str(port), *files], tmp_path / "node-opcua.log")
    try:
        live = start_serve(tmp_path / "data", "--config", str(config))
        try:
            served = run_trusted(live, "machines.js")["machines"]
            served_tree = run_trusted(live, "cell_tree.js")["nodes"]
        finally:
            live.stop()
        loaded = run_node("machines.js", f"opc.tcp://127.0.0.1:{port}/")["machines"]
        loaded_tree = run_node("cell_tree.js", f"opc.tcp://127.0.0.1:{port}/")["nodes"]
    finally:
        bare.stop()
    assert set(served) == {"Robot1", "Filler1"}
    # The export leaves DateTime values out (decision 32: most are stamps of the moment), the
    # configured InitialOperationDate too: node-opcua gives the variable its own default.
    assert served["Filler1"]["identification"].pop("InitialOperationDate") == "2021-09-01T00:00:00.000Z"
    assert loaded["Filler1"]["identification"].pop("InitialOperationDate") == "1601-01-01T00:00:00.000Z"
    assert loaded == served  # identification, state and mode as a freshly started server has them
    assert served["Filler1"]["identification"]["Location"] == "Plant 1/Hall 3"
    found = differences(served_tree, loaded_tree)  # every node below the machines, every reference
    assert not found, "\n".join(found)
    machinery = [k for k in loaded_tree if ".MachineryBuildingBlocks.Machinery" in k]
    assert len(machinery) >= 20  # the two state machines of each machine with their members


async def test_a_gateway_robot_whose_controller_is_lost_is_not_available(tmp_path: Path) -> None:
    """The shipped modbus-robot cell: its controller (the example Modbus controller) killed and back."""
    from test_gateway_robot import PLC as Controller
    from test_gateway_robot import cell_text

    controller = Controller(free_port(), 1.0)
    controller.start()
    try:
        await controller.io()  # listening before uacell starts
        path = tmp_path / "cell.toml"
        path.write_text(cell_text(controller.port) + '\n[[machines]]\nname = "Palletizer"\nlocation = "Cell 4"\n')
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (app, client):
            m = await client.get_namespace_index(MACHINERY)
            cell_ns = await client.get_namespace_index("urn:uacell:cell")
            blocks = client.get_node(ua.NodeId("Palletizer.MachineryBuildingBlocks", cell_ns))
            current = await blocks.get_child([f"{m}:MachineryItemState", "0:CurrentState"])
            mode = await blocks.get_child([f"{m}:MachineryOperationMode", "0:CurrentState"])

            async def item_state() -> str:
                return str((await current.read_value()).Text)

            await until(item_state, "NotExecuting", timeout=20.0)  # once the controller answered
            controller.kill()
            await until(item_state, "NotAvailable", timeout=20.0)
            assert (await mode.read_value()).Text == "None"
            seen = await machines(app.endpoint)
            assert seen["Palletizer"]["itemState"] == ["NotAvailable", 0]
            assert seen["Palletizer"]["identification"]["Location"] == "Cell 4"
            controller.start()  # the same port
            await until(item_state, "NotExecuting", timeout=30.0)
            assert (await mode.read_value()).Text == "Processing"
    finally:
        controller.kill()
        for conn in controller.clients:
            conn.close()
