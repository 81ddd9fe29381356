"""Robotics through a real asyncua client over TCP: programs, task control, system operation, alarms.

One server serves the whole module (start-up takes seconds); ``fresh`` brings the robot back to
power off, nothing loaded, no alarm and only the sample programs before each test. Anonymous clients
are engineers here so that programs can be uploaded through FileType.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import Callable
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.common.subscription import Subscription
from conftest import fast_config, start_app
from helpers import (
    Collector,
    delivered,
    raw_call,
    robot_binding,
    robot_cell,
    server_value,
    simulated_robot,
    wait_until,
)

from uacell.core.roles import Role
from uacell.robotics.equipment import ExecutionMode, StopMode
from uacell.server import UacellServer

module_loop = pytest.mark.asyncio(loop_scope="module")
pytestmark = module_loop

CTRL = "Robot1.Controllers.Controller1"
TASK = f"{CTRL}.TaskControls.TaskControl1"
TC = f"{TASK}.TaskControlOperation.TaskControlStateMachine"
READY = f"{TC}.ReadySubstateMachine"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
IDLE_SUB = f"{SO}.IdleSubstateMachine"
EXEC_SUB = f"{SO}.ExecutingSubstateMachine"
PROGRAMS = f"{CTRL}.Programs"
ARM = "Robot1.MotionDevices.Arm1"
COND = f"{CTRL}.SystemOperation.Conditions"
SAMPLES = {"gripper.robot", "palletize.robot", "pick_and_place.robot"}
TIMEOUT = 15.0

# A long program: one short move, then a wait that only a Stop ends (5 s real at time_scale 20).
LONG = "program Long version 1\nmove 10 0 0 0 0 0\nwait 100\n"
# A slow sweep of axis 1 (about 0.5 s real): the sampled positions change several times.
SWEEP = "program Sweep version 3\nspeed 2\nmove 60 0 0 0 0 0\n"


class Events(Collector):
    """Collects events of one subscription; ``wait_for`` returns the first matching one."""

    timeout = TIMEOUT

    def transitions(self, source: ua.NodeId | None = None) -> list[str]:
        return [
            e.Transition.Text
            for e in self.events
            if hasattr(e, "Transition") and (source is None or e.SourceNode == source)
        ]


class Rig:
    app: UacellServer
    client: Client
    ns: int
    rob: int


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def rig(tmp_path_factory):
    config = fast_config(tmp_path_factory.mktemp("robotics") / "data")
    config.server.anonymous_role = "engineer"
    app = await start_app(config)
    client = Client(app.endpoint, timeout=30, watchdog_intervall=30.0)  # as conftest.serving: a loaded machine
    await client.connect()
    await client.load_data_type_definitions()
    r = Rig()
    r.app, r.client = app, client
    r.ns = await client.get_namespace_index("urn:uacell:cell")
    r.rob = await client.get_namespace_index("http://opcfoundation.org/UA/Robotics/")
    try:
        yield r
    finally:
        await client.disconnect()
        await app.stop()


async def _reset(r: Rig) -> None:
    cell = robot_cell(r.app)
    equipment = simulated_robot(r.app)
    for name in list(equipment.active_alarms):
        equipment.clear_alarm(name)
    for cond in cell.system.conditions.values():
        if not cond.acked:
            cell.system.acknowledge(cond.name)
    for task in cell.tasks.values():
        if task.executing:
            if not task.stopping:
                await task.stop(int(StopMode.QUICK_STOP))
            await task.wait_until_not_executing()
        if task.state == "Ready":
            await task.unload_program()
        for module in task.modules:
            await task.unload_module(module.name)
        await task.set_execution_mode(int(ExecutionMode.CYCLE))
    system = cell.system
    if (system.state == "Idle" and system.idle.current == "GettingReady") or system.state == "Ready":
        await system.stand_down()
    async with asyncio.timeout(TIMEOUT):
        while system.state != "Idle" or system.powering_down or system.idle.current != "StandBy":
            await asyncio.sleep(0.01)
    store = robot_binding(r.app).store
    for entry in store.entries():
        if entry.relpath not in SAMPLES and "/" not in entry.relpath:
            store.delete(entry.relpath)
    await r.app.settle()


@pytest_asyncio.fixture(loop_scope="module")
async def fresh(rig):
    await _reset(rig)
    return rig


# --- helpers ---------------------------------------------------------------------------------------
def nid(r: Rig, path: str) -> ua.NodeId:
    return ua.NodeId(path, r.ns)


async def read(r: Rig, path: str):
    return await r.client.get_node(nid(r, path)).read_value()


async def state(r: Rig, path: str) -> str:
    return (await read(r, f"{path}.CurrentState")).Text


async def call_on(r: Rig, obj: ua.NodeId, method: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
    return await raw_call(r.client, obj, method, *args)


async def call(r: Rig, path: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    return await call_on(r, nid(r, path), nid(r, f"{path}.{method}"), *args)


async def status(r: Rig, path: str, method: str, *args: ua.Variant) -> int:
    res = await call(r, path, method, *args)
    assert res.StatusCode.is_good(), (method, res.StatusCode)
    assert res.OutputArguments[0].VariantType == ua.VariantType.Int32
    return res.OutputArguments[0].Value


def s(text: str) -> ua.Variant:
    return ua.Variant(text, ua.VariantType.String)


def mode(value: int) -> ua.Variant:
    return ua.Variant(value, ua.VariantType.Int64)


def xid(nodeid: ua.NodeId, **kw) -> ua.Variant:
    expanded = ua.ExpandedNodeId(nodeid.Identifier, nodeid.NamespaceIndex, nodeid.NodeIdType, **kw)
    return ua.Variant(expanded, ua.VariantType.ExpandedNodeId)


async def subscribe_transitions(r: Rig, *paths: str) -> tuple[Events, Subscription]:
    events = Events()
    sub = await r.client.create_subscription(20, events)
    evtype = r.client.get_node(ua.ObjectIds.TransitionEventType)
    for path in paths:
        await sub.subscribe_events(r.client.get_node(nid(r, path)), evtype)
    return events, sub


def is_transition(name: str, source: ua.NodeId | None = None) -> Callable[[Any], bool]:
    return lambda e: (
        getattr(getattr(e, "Transition", None), "Text", None) == name and (source is None or e.SourceNode == source)
    )


async def wait_state(r: Rig, path: str, wanted: str) -> None:
    async with asyncio.timeout(TIMEOUT):
        while await state(r, path) != wanted:
            await asyncio.sleep(0.02)


async def power_up(r: Rig) -> None:
    assert await status(r, SO, "GetReady") == 0
    await wait_state(r, SO, "Ready")


async def upload(r: Rig, name: str, text: str) -> ua.NodeId:
    """CreateFile + Write + Close through OPC UA; the new FileType node."""
    res = await call(r, PROGRAMS, "CreateFile", s(name), ua.Variant(True, ua.VariantType.Boolean))
    assert res.StatusCode.is_good(), res.StatusCode
    file_id, handle = res.OutputArguments[0].Value, res.OutputArguments[1].Value
    file_node = r.client.get_node(file_id)
    write = (await file_node.get_child("0:Write")).nodeid
    close = (await file_node.get_child("0:Close")).nodeid
    data = ua.Variant(text.encode(), ua.VariantType.ByteString)
    res = await call_on(r, file_id, write, ua.Variant(handle, ua.VariantType.UInt32), data)
    assert res.StatusCode.is_good(), res.StatusCode
    res = await call_on(r, file_id, close, ua.Variant(handle, ua.VariantType.UInt32))
    assert res.StatusCode.is_good(), res.StatusCode
    return file_id


async def program_file(r: Rig, name: str) -> ua.NodeId:
    for child in await r.client.get_node(nid(r, PROGRAMS)).get_children():
        if (await child.read_browse_name()).Name == name:
            return child.nodeid
    raise AssertionError(f"no {name} in Programs")


# --- loading ---------------------------------------------------------------------------------------
async def test_program_uploaded_through_filetype_then_loaded_by_node_id(fresh):
    r = fresh
    file_id = await upload(r, "sweep.robot", SWEEP)
    events, sub = await subscribe_transitions(r, TC)
    assert await status(r, TC, "LoadByNodeId", xid(file_id)) == 0
    await events.wait_for(is_transition("IdleToReady"))
    assert await state(r, TC) == "Ready"
    assert await state(r, READY) == "AtProgramStart"
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramName") == "Sweep"
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramLoaded") is True
    assert await read(r, f"{TC}.LastTransitionReason") == 1
    # the same by namespace URI instead of index
    by_uri = ua.ExpandedNodeId(file_id.Identifier, 0, file_id.NodeIdType, "urn:uacell:cell")
    assert await status(r, TC, "LoadByNodeId", ua.Variant(by_uri, ua.VariantType.ExpandedNodeId)) == 0
    await sub.delete()


async def test_load_by_name_and_the_module_appears_under_task_modules(fresh):
    r = fresh
    assert await status(r, TC, "LoadByName", s("gripper")) == 0
    assert await state(r, TC) == "Idle"  # a module alone makes no program
    module = f"{TASK}.TaskModules.Gripper"
    assert await read(r, f"{module}.Name") == "Gripper"
    assert await read(r, f"{module}.Version") == "1.2"
    assert await read(r, f"{module}.IsReferenced") is False
    folder = r.client.get_node(nid(r, f"{TASK}.TaskModules"))
    refs = await folder.get_references(ua.ObjectIds.Organizes)
    assert [ref.BrowseName.Name for ref in refs] == ["Gripper"]
    assert await status(r, TC, "LoadByName", s("pick_and_place")) == 0
    assert await state(r, TC) == "Ready"
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramName") == "PickAndPlace"
    assert await read(r, f"{module}.IsReferenced") is True


async def test_unknown_name_is_minus_one_with_idle_to_idle_reason_error(fresh):
    r = fresh
    events, sub = await subscribe_transitions(r, TC)
    assert await status(r, TC, "LoadByName", s("no_such_program")) == -1
    ev = await events.wait_for(is_transition("IdleToIdle"))
    assert ev.FromState.Text == "Idle" and ev.ToState.Text == "Idle"
    assert ev.SourceNode == nid(r, TC)
    await delivered(r.app, events, nid(r, TC))
    assert events.transitions() == ["IdleToIdle"]  # one event for the one transition
    assert await state(r, TC) == "Idle"
    assert (await read(r, f"{TC}.LastTransition")).Text == "IdleToIdle"
    assert await read(r, f"{TC}.LastTransitionReason") == 4
    await sub.delete()


async def test_invalid_content_is_minus_two_with_idle_to_idle(fresh):
    r = fresh
    await upload(r, "broken.robot", "program Broken\nmove 999 0 0 0 0 0\n")
    events, sub = await subscribe_transitions(r, TC)
    assert await status(r, TC, "LoadByName", s("broken")) == -2
    await events.wait_for(is_transition("IdleToIdle"))
    assert await read(r, f"{TC}.LastTransitionReason") == 4
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramLoaded") is False
    await sub.delete()


@pytest.mark.parametrize(
    "case",
    ["null", "remote", "unknown-uri", "no-node", "not-a-file", "directory-node"],
)
async def test_bad_node_ids_answer_bad_codes_with_argument_result_and_no_transition(fresh, case):
    r = fresh
    before = await read(r, f"{TC}.LastTransition")
    sample = await program_file(r, "palletize.robot")
    variants = {
        "null": xid(ua.NodeId()),
        "remote": xid(sample, ServerIndex=2),
        "unknown-uri": ua.Variant(
            ua.ExpandedNodeId(sample.Identifier, 0, sample.NodeIdType, "urn:nowhere"), ua.VariantType.ExpandedNodeId
        ),
        "no-node": xid(ua.NodeId("nothing.here", r.ns)),
        "not-a-file": xid(nid(r, ARM)),
        "directory-node": xid(nid(r, PROGRAMS)),
    }
    expected = (
        ua.StatusCodes.BadNodeIdInvalid
        if case in ("null", "remote", "unknown-uri")
        else (ua.StatusCodes.BadNodeIdUnknown)
    )
    events, sub = await subscribe_transitions(r, TC)
    res = await call(r, TC, "LoadByNodeId", variants[case])
    assert res.StatusCode.value == expected
    assert [c.value for c in res.InputArgumentResults] == [expected]
    await delivered(r.app, events, nid(r, TC))
    assert events.transitions() == []
    assert await state(r, TC) == "Idle"
    assert await read(r, f"{TC}.LastTransition") == before
    await sub.delete()


async def test_load_in_ready_replaces_and_a_failure_keeps_the_old_program(fresh):
    r = fresh
    await upload(r, "long.robot", LONG)
    assert await status(r, TC, "LoadByName", s("long")) == 0
    events, sub = await subscribe_transitions(r, TC, READY)
    assert await status(r, TC, "LoadByName", s("palletize")) == 0
    assert await state(r, TC) == "Ready"
    assert await state(r, READY) == "AtProgramStart"
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramName") == "Palletize"
    assert await status(r, TC, "LoadByName", s("no_such_program")) == -1
    await upload(r, "broken.robot", "program Broken\nfly 1\n")
    assert await status(r, TC, "LoadByName", s("broken")) == -2
    assert await state(r, TC) == "Ready"
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramName") == "Palletize"
    await delivered(r.app, events, nid(r, TC))
    assert events.transitions() == []  # no IdleToIdle/IdleToReady in Ready
    await sub.delete()


async def test_load_and_unload_in_executing_answer_one_and_change_nothing(fresh):
    r = fresh
    await upload(r, "long.robot", LONG)
    await power_up(r)
    assert await status(r, TC, "LoadByName", s("long")) == 0
    assert await status(r, TC, "Start") == 0
    assert await state(r, TC) == "Executing"
    sample = await program_file(r, "palletize.robot")
    assert await status(r, TC, "LoadByName", s("palletize")) == 1
    assert await status(r, TC, "LoadByNodeId", xid(sample)) == 1
    assert await status(r, TC, "UnloadProgram") == 1
    assert await status(r, TC, "UnloadByName", s("Long")) == 1
    assert await state(r, TC) == "Executing"
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramName") == "Long"
    # the loaded program cannot be deleted or overwritten meanwhile
    file_id = await program_file(r, "long.robot")
    res = await call(r, PROGRAMS, "Delete", ua.Variant(file_id, ua.VariantType.NodeId))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState


# --- running ---------------------------------------------------------------------------------------
async def test_start_runs_the_program_to_its_end_and_the_axes_move(fresh):
    r = fresh
    await upload(r, "sweep.robot", SWEEP)
    await power_up(r)
    assert await status(r, TC, "LoadByName", s("sweep")) == 0
    events, sub = await subscribe_transitions(r, TC, SO)
    axis = r.client.get_node(nid(r, f"{ARM}.Axes.Axis1.ParameterSet.ActualPosition"))
    speed = r.client.get_node(nid(r, f"{ARM}.Axes.Axis1.ParameterSet.ActualSpeed"))
    samples = Events()
    data_sub = await r.client.create_subscription(20, samples)
    await data_sub.subscribe_data_change([axis, speed])
    assert await read(r, f"{ARM}.ParameterSet.InControl") is True
    assert await status(r, TC, "Start") == 0
    assert await state(r, TC) == "Executing"
    await events.wait_for(is_transition("ExecutingToReady", nid(r, TC)))
    assert events.transitions(nid(r, TC)) == ["ReadyToExecuting", "ExecutingToReady"]
    # decision 19: the system followed the task control
    await events.wait_for(is_transition("ExecutingToReady", nid(r, SO)))
    assert events.transitions(nid(r, SO)) == ["ReadyToExecuting", "ExecutingToReady"]
    assert await read(r, f"{TC}.LastTransitionReason") == 5
    assert await state(r, READY) == "AtProgramStart"
    # the sampler publishes the resting arm once it notices
    await wait_until(lambda: server_value(r.app, axis.nodeid) == pytest.approx(60.0))
    await wait_until(lambda: server_value(r.app, speed.nodeid) == 0.0)
    assert await axis.read_value() == pytest.approx(60.0)
    assert await speed.read_value() == 0.0
    positions = [v for n, v in samples.events if n == axis]
    speeds = [v for n, v in samples.events if n == speed]
    assert len(set(positions)) >= 3, positions  # intermediate positions were published
    assert all(0.0 <= p <= 60.0 for p in positions)
    assert max(speeds) == pytest.approx(288.0 * 0.02, rel=0.01)
    await data_sub.delete()
    await sub.delete()


async def test_stop_suspends_and_reset_to_program_start(fresh):
    r = fresh
    await upload(r, "long.robot", LONG)
    await power_up(r)
    assert await status(r, TC, "LoadByName", s("long")) == 0
    events, sub = await subscribe_transitions(r, TC, READY)
    assert await status(r, TC, "Stop", mode(0)) == 1  # not executing
    assert await status(r, TC, "Start") == 0
    res = await call(r, TC, "Stop", mode(9))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert [c.value for c in res.InputArgumentResults] == [ua.StatusCodes.BadInvalidArgument]
    assert await status(r, TC, "Stop", mode(int(StopMode.QUICK_STOP))) == 0
    await events.wait_for(is_transition("ExecutingToReady"))
    assert await read(r, f"{TC}.LastTransitionReason") == 1
    assert await state(r, READY) == "Suspended"
    assert await status(r, READY, "ResetToProgramStart") == 0
    await events.wait_for(is_transition("SuspendedToProgramStart"))
    assert await state(r, READY) == "AtProgramStart"
    assert await status(r, READY, "ResetToProgramStart") == 0  # already there: no transition
    await delivered(r.app, events, nid(r, READY))
    assert events.transitions(nid(r, READY)).count("SuspendedToProgramStart") == 1
    await sub.delete()


async def test_execution_mode_is_writable_except_while_executing_and_step_runs_one_instruction(fresh):
    r = fresh
    await upload(r, "long.robot", LONG)
    await power_up(r)
    assert await status(r, TC, "LoadByName", s("long")) == 0
    node = r.client.get_node(nid(r, f"{TASK}.ParameterSet.ExecutionMode"))
    await node.write_value(ua.Variant(int(ExecutionMode.STEP), ua.VariantType.Int32))
    assert await node.read_value() == 2
    assert robot_cell(r.app).tasks["TaskControl1"].execution_mode is ExecutionMode.STEP
    with pytest.raises(ua.UaStatusCodeError) as err:
        await node.write_value(ua.Variant(7, ua.VariantType.Int32))
    assert err.value.code == ua.StatusCodes.BadOutOfRange
    events, sub = await subscribe_transitions(r, TC)
    assert await status(r, TC, "Start") == 0  # STEP: the first move only
    await events.wait_for(is_transition("ExecutingToReady"))
    assert await read(r, f"{TC}.LastTransitionReason") == 3
    assert await state(r, READY) == "Suspended"
    await node.write_value(ua.Variant(int(ExecutionMode.CYCLE), ua.VariantType.Int32))
    assert await status(r, TC, "Start") == 0  # now the wait of 100 s
    with pytest.raises(ua.UaStatusCodeError) as err:
        await node.write_value(ua.Variant(int(ExecutionMode.CONTINUOUS), ua.VariantType.Int32))
    assert err.value.code == ua.StatusCodes.BadInvalidState
    assert await node.read_value() == 0
    await sub.delete()


# A program whose instructions take turns long enough (about 0.3 s real each) to watch the line move.
LINES = "program Lines version 1\nmove 10 0 0 0 0 0\nwait 6\nmove 0 0 0 0 0 0\nwait 6\n"


async def test_current_line_and_program_pointer_follow_the_run_and_return_to_zero(fresh):
    r = fresh
    await upload(r, "lines.robot", LINES)
    await power_up(r)
    assert await status(r, TC, "LoadByName", s("lines")) == 0
    line = r.client.get_node(nid(r, f"{TASK}.ParameterSet.CurrentLine"))
    pointer = r.client.get_node(nid(r, f"{TASK}.ParameterSet.ProgramPointer"))
    # Server-defined, read-only UInt32 variables in uacell's namespace, said so in their Description.
    for node in (line, pointer):
        assert await node.read_data_type() == ua.NodeId(ua.ObjectIds.UInt32)
        assert (await node.read_browse_name()).NamespaceIndex == r.ns
        assert (await node.read_description()).Text.startswith("uacell: ")
        # both are historized (uacell.core.datasets): they may be read, and history-read, not written
        assert await node.get_access_level() == {ua.AccessLevel.CurrentRead, ua.AccessLevel.HistoryRead}
        with pytest.raises(ua.UaStatusCodeError):
            await node.write_value(ua.Variant(7, ua.VariantType.UInt32))
    assert (await line.read_value(), await pointer.read_value()) == (0, 0)
    seen = Events()
    data_sub = await r.client.create_subscription(20, seen)
    await data_sub.subscribe_data_change([line, pointer])
    events, sub = await subscribe_transitions(r, TC)
    assert await status(r, TC, "Start") == 0
    # Read while it runs: the first wait (line 3, step 1), then the second (line 5, step 3).
    async with asyncio.timeout(TIMEOUT):
        while (await line.read_value(), await pointer.read_value()) != (3, 1):
            await asyncio.sleep(0.01)
        while (await line.read_value(), await pointer.read_value()) != (5, 3):
            await asyncio.sleep(0.01)
    await events.wait_for(is_transition("ExecutingToReady"))
    await wait_until(lambda: server_value(r.app, line.nodeid) == 0)
    assert (await line.read_value(), await pointer.read_value()) == (0, 0)  # at the program start again
    await seen.wait_for(lambda _e: [v for n, v in seen.events if n == line][-1:] == [0])
    values = [v for n, v in seen.events if n == line]
    # The subscriber saw each instruction's line in order (a quick move may be coalesced away), then 0.
    assert values[0] == 0 and values[-1] == 0 and {3, 5} <= set(values), values
    assert [v for v in values if v] == sorted(v for v in values if v), values
    # A Stop keeps the pointer (Start resumes there) and clears the line.
    assert await status(r, TC, "Start") == 0
    async with asyncio.timeout(TIMEOUT):
        while await line.read_value() != 3:
            await asyncio.sleep(0.01)
    assert await status(r, TC, "Stop", mode(int(StopMode.QUICK_STOP))) == 0
    await events.wait_for(lambda e: len(events.transitions(nid(r, TC))) >= 4)
    await wait_until(lambda: server_value(r.app, line.nodeid) == 0)
    assert (await line.read_value(), await pointer.read_value()) == (0, 1)
    assert await status(r, READY, "ResetToProgramStart") == 0
    await wait_until(lambda: server_value(r.app, pointer.nodeid) == 0)
    await data_sub.delete()
    await sub.delete()


# --- unloading -------------------------------------------------------------------------------------
async def test_every_unload(fresh):
    r = fresh
    tm = f"{TASK}.TaskModules"
    events, sub = await subscribe_transitions(r, TC)
    # UnloadByNodeId with the TaskModule node; a module does not change the state
    assert await status(r, TC, "LoadByName", s("gripper")) == 0
    assert await status(r, TC, "UnloadByNodeId", xid(nid(r, f"{tm}.Gripper"))) == 0
    await r.app.settle()
    assert await r.client.get_node(nid(r, f"{tm}")).get_children() == []
    assert await state(r, TC) == "Idle"
    # UnloadByName of a module in use: -4; of an unknown name: -1
    assert await status(r, TC, "LoadByName", s("gripper")) == 0
    assert await status(r, TC, "LoadByName", s("pick_and_place")) == 0
    assert await status(r, TC, "UnloadByName", s("Gripper")) == -4
    assert await status(r, TC, "UnloadByName", s("Nothing")) == -1
    # UnloadByName of the program: everything, ReadyToIdle
    assert await status(r, TC, "UnloadByName", s("PickAndPlace")) == 0
    assert await state(r, TC) == "Idle"
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramLoaded") is False
    assert await read(r, f"{TASK}.ParameterSet.TaskProgramName") == ""
    assert robot_cell(r.app).tasks["TaskControl1"].modules == []
    # UnloadProgram
    assert await status(r, TC, "UnloadProgram") == 1  # nothing loaded
    assert await status(r, TC, "LoadByName", s("palletize")) == 0
    assert await status(r, TC, "UnloadProgram") == 0
    assert await state(r, TC) == "Idle"
    # UnloadByNodeId with the program's FileType node; a file that is not loaded: -1
    file_id = await program_file(r, "palletize.robot")
    other = await program_file(r, "pick_and_place.robot")
    assert await status(r, TC, "LoadByNodeId", xid(file_id)) == 0
    assert await status(r, TC, "UnloadByNodeId", xid(other)) == -1
    res = await call(r, TC, "UnloadByNodeId", xid(nid(r, ARM)))
    assert res.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown
    assert await status(r, TC, "UnloadByNodeId", xid(file_id)) == 0
    assert await state(r, TC) == "Idle"
    await events.wait_for(lambda e: events.transitions().count("ReadyToIdle") == 3)
    await sub.delete()


async def test_deleting_the_loaded_program_is_bad_invalid_state_until_unloaded(fresh):
    r = fresh
    file_id = await upload(r, "sweep.robot", SWEEP)
    assert await status(r, TC, "LoadByNodeId", xid(file_id)) == 0
    res = await call(r, PROGRAMS, "Delete", ua.Variant(file_id, ua.VariantType.NodeId))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    open_ = (await r.client.get_node(file_id).get_child("0:Open")).nodeid
    res = await call_on(r, file_id, open_, ua.Variant(6, ua.VariantType.Byte))  # write + erase
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    assert await status(r, TC, "UnloadProgram") == 0
    res = await call(r, PROGRAMS, "Delete", ua.Variant(file_id, ua.VariantType.NodeId))
    assert res.StatusCode.is_good()


# --- system operation ------------------------------------------------------------------------------
async def test_system_operation_walk(fresh):
    r = fresh
    events, sub = await subscribe_transitions(r, SO, IDLE_SUB, EXEC_SUB, TC)
    await upload(r, "long.robot", LONG)
    assert await status(r, TC, "LoadByName", s("long")) == 0
    assert await status(r, TC, "Start") == 1  # decision 19: the robot is not powered
    assert await status(r, SO, "Start") == 1
    assert await status(r, SO, "StandDown") == 1
    assert await status(r, SO, "GetReady") == 0
    await events.wait_for(is_transition("StandByToGettingReady"))
    await events.wait_for(is_transition("IdleToReady", nid(r, SO)))
    assert await status(r, SO, "GetReady") == 1
    # SystemOperation Start starts the task control (reason 3 System on the task control)
    assert await status(r, SO, "Start") == 0
    assert await state(r, SO) == "Executing"
    assert await state(r, EXEC_SUB) == "Running"
    assert await state(r, TC) == "Executing"
    assert await read(r, f"{TC}.LastTransitionReason") == 3
    assert await status(r, SO, "StandDown") == 1  # something executes
    res = await call(r, SO, "Stop", mode(42))  # decision 17: not in PossibleStopModes
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert [c.value for c in res.InputArgumentResults] == [ua.StatusCodes.BadInvalidArgument]
    assert await state(r, EXEC_SUB) == "Running"
    assert await status(r, SO, "Stop", mode(0)) == 0
    await events.wait_for(is_transition("RunningToStopping"))
    await events.wait_for(is_transition("ExecutingToReady", nid(r, SO)))
    assert await read(r, f"{SO}.LastTransitionReason") == 1
    assert await state(r, TC) == "Ready"
    assert await state(r, READY) == "Suspended"
    assert await status(r, SO, "StandDown") == 0
    await events.wait_for(is_transition("ReadyToIdle", nid(r, SO)))
    assert await state(r, IDLE_SUB) == "StandBy"
    assert events.transitions(nid(r, SO)) == ["IdleToReady", "ReadyToExecuting", "ExecutingToReady", "ReadyToIdle"]
    assert await read(r, f"{ARM}.ParameterSet.InControl") is False
    await sub.delete()


# --- Executable (decision 4) -------------------------------------------------------------------------
TC_ALL = ("LoadByNodeId", "LoadByName", "UnloadProgram", "UnloadByNodeId", "UnloadByName", "Start", "Stop")
SO_ALL = ("GetReady", "StandDown", "Start", "Stop")


async def executables(r: Rig) -> dict[str, bool]:
    """Executable of every Robotics method, as a client reads it ('TC.Start', 'SO.Start', 'Reset')."""
    await r.app.settle()
    targets = [(f"TC.{m}", f"{TC}.{m}") for m in TC_ALL] + [(f"SO.{m}", f"{SO}.{m}") for m in SO_ALL]
    targets.append(("Reset", f"{READY}.ResetToProgramStart"))
    out = {}
    for key, path in targets:
        node = r.client.get_node(nid(r, path))
        executable = (await node.read_attribute(ua.AttributeIds.Executable)).Value.Value
        user = (await node.read_attribute(ua.AttributeIds.UserExecutable)).Value.Value
        assert user == executable, key  # the engineer may call them all
        out[key] = executable
    return out


def only(*true: str) -> dict[str, bool]:
    keys = [f"TC.{m}" for m in TC_ALL] + [f"SO.{m}" for m in SO_ALL] + ["Reset"]
    return {k: k in true for k in keys}


async def test_executable_attribute_matches_what_a_call_does(fresh):
    r = fresh
    # a wait longer than the test (3 min at time_scale 20): the stop at its end stays Stopping until
    # the quick stop
    # (with LONG's 5 s, a slow machine once saw the stop complete between two reads of Executable)
    await upload(r, "long.robot", LONG.replace("wait 100\n", "wait 3600\n"))
    # Idle, robot off: only loading and GetReady can succeed
    assert await executables(r) == only("TC.LoadByNodeId", "TC.LoadByName", "SO.GetReady")
    assert await status(r, TC, "UnloadProgram") == 1 and await status(r, SO, "Start") == 1
    assert await status(r, TC, "LoadByName", s("gripper")) == 0  # a module in Idle: it can be unloaded
    assert await executables(r) == only(
        "TC.LoadByNodeId", "TC.LoadByName", "TC.UnloadByNodeId", "TC.UnloadByName", "SO.GetReady"
    )
    assert await status(r, TC, "UnloadByName", s("Gripper")) == 0
    # Ready with a program, robot off: Start would answer 1 (decision 19)
    assert await status(r, TC, "LoadByName", s("long")) == 0
    ready_off = only(
        "TC.LoadByNodeId",
        "TC.LoadByName",
        "TC.UnloadProgram",
        "TC.UnloadByNodeId",
        "TC.UnloadByName",
        "Reset",
        "SO.GetReady",
    )
    assert await executables(r) == ready_off
    assert await status(r, TC, "Start") == 1
    # robot on: both Starts and StandDown; no GetReady
    await power_up(r)
    ready_on = {**ready_off, "SO.GetReady": False, "TC.Start": True, "SO.Start": True, "SO.StandDown": True}
    assert await executables(r) == ready_on
    assert await status(r, SO, "GetReady") == 1
    # an active alarm: no Start (Status 3) until it is cleared and acknowledged
    equipment, system = simulated_robot(r.app), robot_cell(r.app).system
    equipment.raise_alarm("EmergencyStop")
    assert await executables(r) == {**ready_on, "TC.Start": False, "SO.Start": False}
    assert await status(r, TC, "Start") == 3
    equipment.clear_alarm("EmergencyStop")
    system.acknowledge("EmergencyStop")
    assert await executables(r) == ready_on
    # Executing: only the Stops
    assert await status(r, TC, "Start") == 0
    assert await executables(r) == only("TC.Stop", "SO.Stop")
    assert await status(r, TC, "LoadByName", s("long")) == 1
    assert await status(r, READY, "ResetToProgramStart") == 1
    # stopping (the wait finishes its instruction only after a stop at the end of it): nothing. The
    # program has reached its wait (line 3) first: a stop during the move before it ended with the move
    # on a loaded machine, and the task was Ready again before Executable was read
    task = robot_cell(r.app).tasks["TaskControl1"]
    await wait_until(lambda: task.current_line == 3)
    assert await status(r, TC, "Stop", mode(int(StopMode.END_OF_INSTRUCTION))) == 0
    assert await executables(r) == only()
    assert await status(r, TC, "Stop", mode(0)) == 1 and await status(r, SO, "Stop", mode(0)) == 1
    await robot_cell(r.app).equipment.stop("TaskControl1", StopMode.QUICK_STOP)
    await wait_state(r, TC, "Ready")
    assert await executables(r) == ready_on  # also refreshed when the state changes without a call


async def test_stop_modes_and_motion_devices_are_published(fresh):
    r = fresh
    for machine in (TC, SO):
        modes = await read(r, f"{machine}.PossibleStopModes")
        assert [m.Value for m in modes] == [1, 2, 3, 4, 5]
        assert modes[0].DisplayName.Text == "OnPath"
        assert await read(r, f"{machine}.ConfiguredDefaultStopMode") == 1
    assert await read(r, f"{TASK}.TaskControlOperation.MotionDevicesUnderControl") == [nid(r, ARM)]
    refs = await r.client.get_node(nid(r, TASK)).get_references(refs=ua.ObjectIds.HierarchicalReferences)
    controls = [ref for ref in refs if ref.NodeId == nid(r, ARM)]
    assert controls and controls[0].ReferenceTypeId.NamespaceIndex == r.rob  # Controls, hierarchical


# --- alarms (decision 18) ----------------------------------------------------------------------------
async def test_active_alarm_is_status_3_unacknowledged_is_4_and_acknowledge_clears(fresh):
    r = fresh
    cond = f"{COND}.EmergencyStop"
    events = Events()
    sub = await r.client.create_subscription(20, events)
    alarm_type = r.client.get_node(ua.ObjectIds.AlarmConditionType)
    await sub.subscribe_events(r.client.get_node(ua.ObjectIds.Server), alarm_type)
    # an admin raises the alarm through the server-specific method
    manager = r.app.server.iserver.user_manager
    policy = manager.policy
    manager.policy = dataclasses.replace(policy, anonymous_role=Role.ADMIN)
    admin = Client(r.app.endpoint, timeout=30)
    await admin.connect()
    simulate = nid(r, CTRL), nid(r, f"{CTRL}.SimulateAlarm"), s("EmergencyStop")
    try:
        res = await raw_call(admin, *simulate, ua.Variant(True, ua.VariantType.Boolean))
        assert res.StatusCode.is_good(), res.StatusCode
    finally:
        await admin.disconnect()
        manager.policy = policy
    # operators may not simulate alarms (engineers and admins may)
    manager.policy = dataclasses.replace(policy, anonymous_role=Role.OPERATOR)
    operator = Client(r.app.endpoint, timeout=30)
    await operator.connect()
    try:
        res = await raw_call(operator, *simulate, ua.Variant(False, ua.VariantType.Boolean))
        assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    finally:
        await operator.disconnect()
        manager.policy = policy
    ev = await events.wait_for(lambda e: getattr(e, "ConditionName", None) == "EmergencyStop")
    assert getattr(ev, "ActiveState/Id") is True and getattr(ev, "AckedState/Id") is False
    assert ev.Retain is True
    await r.app.settle()
    assert await read(r, f"{cond}.ActiveState.Id") is True
    assert await read(r, f"{cond}.AckedState.Id") is False
    assert await read(r, f"{cond}.Retain") is True
    assert await status(r, SO, "GetReady") == 3
    simulated_robot(r.app).clear_alarm("EmergencyStop")
    await r.app.settle()
    assert await read(r, f"{cond}.ActiveState.Id") is False
    assert await status(r, SO, "GetReady") == 4
    # Acknowledge with a wrong EventId, then with the condition's current one
    ack = nid(r, f"{cond}.Acknowledge")
    comment = ua.Variant(ua.LocalizedText("reset the e-stop"), ua.VariantType.LocalizedText)
    res = await call_on(r, nid(r, cond), ack, ua.Variant(b"nope", ua.VariantType.ByteString), comment)
    assert res.StatusCode.value == ua.StatusCodes.BadEventIdUnknown
    event_id = await read(r, f"{cond}.EventId")
    # clients usually name the type's Acknowledge (AcknowledgeableConditionType, i=9111)
    type_ack = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
    res = await call_on(r, nid(r, cond), type_ack, ua.Variant(event_id, ua.VariantType.ByteString), comment)
    assert res.StatusCode.is_good(), res.StatusCode
    await r.app.settle()
    assert await read(r, f"{cond}.AckedState.Id") is True
    assert await read(r, f"{cond}.Retain") is False
    res = await call_on(r, nid(r, cond), ack, ua.Variant(event_id, ua.VariantType.ByteString), comment)
    assert res.StatusCode.value == ua.StatusCodes.BadConditionBranchAlreadyAcked
    await events.wait_for(lambda e: getattr(e, "AckedState/Id", None) is True)
    assert await status(r, SO, "GetReady") == 0
    await sub.delete()


async def test_alarm_while_executing_stops_the_program_with_reason_error_and_start_answers_3(fresh):
    r = fresh
    await upload(r, "long.robot", LONG)
    await power_up(r)
    assert await status(r, TC, "LoadByName", s("long")) == 0
    events, sub = await subscribe_transitions(r, TC)
    assert await status(r, TC, "Start") == 0
    simulated_robot(r.app).raise_alarm("CollisionDetected")
    await events.wait_for(is_transition("ExecutingToReady"))
    assert await read(r, f"{TC}.LastTransitionReason") == 4
    assert await status(r, TC, "Start") == 3
    assert await status(r, SO, "Start") == 3
    with contextlib.suppress(Exception):
        await sub.delete()
