"""A call's cost does not grow with the cell: Executable is re-evaluated only for the machines the call
(or a change) touched, and a call naming a method declaration resolves through an index.

One server with two robots (two task controls each) and two PackML units; every bound method's
``executable()`` is wrapped to count its evaluations, per robot / unit.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import AsyncIterator
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config

from uacell.binding.cell import sized_cell
from uacell.packml.binding import UNITS
from uacell.server import UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

TIMEOUT = 15.0


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def cell(tmp_path_factory) -> AsyncIterator[tuple[UacellServer, Client, Counter[str]]]:
    config = fast_config(tmp_path_factory.mktemp("cost") / "data")
    app = await start_app_with(config)
    counts: Counter[str] = Counter()
    for bound in app.dispatcher.methods.values():
        if bound.executable is not None:
            owner = app.server.get_node(bound.object_id).nodeid.Identifier.split(".")[0]
            bound.executable = _counting(bound.executable, owner, counts)
    client = Client(app.endpoint, timeout=30)
    await client.connect()
    try:
        yield app, client, counts
    finally:
        await client.disconnect()
        await app.stop()


async def start_app_with(config) -> UacellServer:
    server = UacellServer(config, parts=sized_cell(units=2, robots=2, task_controls=2))
    await server.setup()
    await server.start()
    return server


def _counting(executable, owner: str, counts: Counter[str]):
    def counted() -> bool:
        counts[owner] += 1
        return executable()

    return counted


def node(app: UacellServer, path: str) -> ua.NodeId:
    return ua.NodeId(path, app.cell.instantiator.ns)


async def call(app: UacellServer, client: Client, obj: str, method: str, *args: ua.Variant) -> Any:
    """The method's output: asyncua hands a single output argument back as itself, several as a list."""
    obj_id = node(app, obj)
    method_id = app.dispatcher.method_of(obj_id, method)
    return await client.get_node(obj_id).call_method(method_id, *args)


async def executable(client: Client, app: UacellServer, obj: str, method: str) -> bool:
    method_id = app.dispatcher.method_of(node(app, obj), method)
    dv = await client.get_node(method_id).read_attribute(ua.AttributeIds.Executable)
    return bool(dv.Value.Value)


async def quiet(app: UacellServer, counts: Counter[str]) -> None:
    await app.settle()
    counts.clear()


def tc(robot: int, task: int) -> str:
    return (
        f"Robot{robot}.Controllers.Controller{robot}.TaskControls.TaskControl{task}"
        ".TaskControlOperation.TaskControlStateMachine"
    )


async def test_a_packml_call_evaluates_only_its_own_unit(cell):
    app, client, counts = cell
    await quiet(app, counts)
    await call(app, client, "Filler1", "SetMachSpeed", ua.Variant(90.0, ua.VariantType.Float))
    # nothing a unit's Executable depends on moved: not even Filler1's methods are evaluated (a call
    # that moves its machines evaluates them: test_a_unit_is_re_evaluated_only_when_...)
    assert counts["Filler1"] == counts["Filler2"] == 0
    assert counts["Robot1"] == counts["Robot2"] == 0
    speed = await client.get_node(node(app, "Filler1.Status.MachSpeed")).read_value()
    assert speed == pytest.approx(90.0)


async def test_a_robotics_call_evaluates_only_its_own_controller_and_executable_follows(cell):
    app, client, counts = cell
    await quiet(app, counts)
    assert await executable(client, app, tc(1, 2), "UnloadProgram") is False
    result = await call(app, client, tc(1, 2), "LoadByName", ua.Variant("pick_and_place", ua.VariantType.String))
    assert result == 0
    # LoadByName made UnloadProgram executable on that task control, and only there
    assert await executable(client, app, tc(1, 2), "UnloadProgram") is True
    assert await executable(client, app, tc(1, 1), "UnloadProgram") is False
    assert await executable(client, app, tc(2, 2), "UnloadProgram") is False
    assert counts["Robot1"] > 0
    assert counts["Robot2"] == 0
    assert counts["Filler1"] == counts["Filler2"] == 0
    counts.clear()
    result = await call(app, client, tc(1, 2), "UnloadProgram")
    assert result == 0
    assert await executable(client, app, tc(1, 2), "UnloadProgram") is False
    assert counts["Robot2"] == counts["Filler1"] == counts["Filler2"] == 0


async def test_a_change_outside_calls_refreshes_only_its_unit(cell):
    app, client, counts = cell
    await quiet(app, counts)
    unit = app.registry(UNITS)["Filler2"].unit
    assert await executable(client, app, "Filler2", "SetUnitMode") is True
    before = await executable(client, app, "Filler2.BaseStateMachine", "Abort")
    unit.abort()  # the model changes outside any call: Aborting, then Aborted after the acting time
    async with asyncio.timeout(TIMEOUT):
        while await executable(client, app, "Filler2.BaseStateMachine", "Clear") is not True:
            await asyncio.sleep(0.05)
    assert before is True
    assert await executable(client, app, "Filler2.BaseStateMachine", "Abort") is False
    assert counts["Filler2"] > 0
    assert counts["Filler1"] == counts["Robot1"] == counts["Robot2"] == 0
    unit.clear()
    async with asyncio.timeout(TIMEOUT):  # until Clearing is over: no transition left for the next test
        while unit.state != "Stopped" or await executable(client, app, "Filler2.BaseStateMachine", "Abort") is not True:
            await asyncio.sleep(0.05)


async def test_a_call_naming_the_declaration_reaches_the_named_object(cell):
    app, client, counts = cell
    await quiet(app, counts)
    instance = app.dispatcher.method_of(node(app, "Filler2"), "SetMachSpeed")
    declaration = app.dispatcher.declarations[instance]
    assert declaration.NamespaceIndex != app.cell.instantiator.ns  # the type's method, not Filler2's
    await client.get_node(node(app, "Filler2")).call_method(declaration, ua.Variant(77.0, ua.VariantType.Float))
    f1 = await client.get_node(node(app, "Filler1.Status.MachSpeed")).read_value()
    f2 = await client.get_node(node(app, "Filler2.Status.MachSpeed")).read_value()
    assert f2 == pytest.approx(77.0)
    assert f1 != pytest.approx(77.0)
    # nothing Filler2's Executable depends on changed (executable_inputs): not even its methods are
    # re-evaluated; Filler1's never are
    assert counts["Filler2"] == counts["Filler1"] == 0
    # the declaration on an object that does not have the method is refused
    with pytest.raises(ua.UaStatusCodeError) as err:
        await client.get_node(node(app, "Robot1")).call_method(declaration, ua.Variant(1.0, ua.VariantType.Float))
    assert err.value.code in (ua.StatusCodes.BadMethodInvalid, ua.StatusCodes.BadNotImplemented)


async def test_a_unit_is_re_evaluated_only_when_what_executable_depends_on_changed(cell):
    """SetMachSpeed changes nothing a unit's Executable depends on: no evaluation; Reset moves the
    machines: the unit's methods (only) are evaluated again."""
    app, client, counts = cell
    await quiet(app, counts)
    await call(app, client, "Filler1", "SetMachSpeed", ua.Variant(90.0, ua.VariantType.Float))
    await app.publisher.flush()  # what the call published, and the idle hook (not settle: it evaluates all)
    assert await client.get_node(node(app, "Filler1.Status.MachSpeed")).read_value() == pytest.approx(90.0)
    assert counts["Filler1"] == counts["Filler2"] == 0
    machine = "Filler1.BaseStateMachine.MachineState"
    assert await executable(client, app, machine, "Reset") is True  # Filler1 is in Stopped
    await call(app, client, machine, "Reset")
    await app.publisher.flush()
    assert counts["Filler1"] > 0 and counts["Filler2"] == counts["Robot1"] == counts["Robot2"] == 0
    assert await executable(client, app, machine, "Reset") is False  # refreshed: not in Resetting or Idle
