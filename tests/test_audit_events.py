"""Who caused a transition: AuditUpdateStateEvents through a real asyncua client over TCP.

A transition a client's method call causes fires, right after its TransitionEvent, an
``AuditUpdateStateEventType`` event naming the user (OPC 10000-16 4.4.18); so does a transition that
completes what the call asked for after the call returned (an acting state completing, the robot
powered up or down, a stopped program's run ending: decision 38). One that follows by itself (a
program ending, production completing) fires none.
"""

from __future__ import annotations

import contextvars
from datetime import datetime
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import Collector, delivered, raw_call, wait_until

from uacell.core.background import Background
from uacell.packml.binding import UNITS
from uacell.security.users import UserStore

module_loop = pytest.mark.asyncio(loop_scope="module")
pytestmark = module_loop

PASSWORD = "pw-audit-1"
MACHINE = "Filler1.BaseStateMachine.MachineState"
EXECUTE = f"{MACHINE}.ExecuteState"
CTRL = "Robot1.Controllers.Controller1"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
TC = f"{CTRL}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
SHORT = "program Short version 1\nmove 10 0 0 0 0 0\nwait 4\nmove 0 0 0 0 0 0\n"
LONG = "program Long version 1\nmove 10 0 0 0 0 0\nwait 600\nmove 0 0 0 0 0 0\n"
ANONYMOUS = "<anonymous>"  # what ``pairs`` says for an audit event whose ClientUserId is null
AUDIT = ua.NodeId(ua.ObjectIds.AuditUpdateStateEventType)
TRANSITION = ua.NodeId(ua.ObjectIds.TransitionEventType)


class Events(Collector):
    def transitions(self) -> list[Any]:  # markers (helpers.delivered) are dropped already
        return [e for e in self.events if e.EventType == TRANSITION]

    def audits(self) -> list[Any]:
        return [e for e in self.events if e.EventType == AUDIT]


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory):
    data = tmp_path_factory.mktemp("audit") / "data"
    UserStore.in_data_dir(data).add("otto", "operator", PASSWORD)
    programs = data / "programs" / "Robot1" / "Controller1"
    programs.mkdir(parents=True)
    (programs / "short.robot").write_text(SHORT)
    (programs / "long.robot").write_text(LONG)
    server = await start_app(fast_config(data))
    yield server
    await server.stop()


async def connect(app, user: str | None = None) -> tuple[Client, int]:
    client = Client(app.endpoint, timeout=30, watchdog_intervall=30.0)  # a loaded machine: no 1 s probe
    if user:
        client.set_user(user)
        client.set_password(PASSWORD)
    await client.connect()
    return client, await client.get_namespace_index("urn:uacell:cell")


async def watch(client: Client, node: ua.NodeId) -> Events:
    """TransitionEvents and AuditUpdateStateEvents of ``node`` (a machine, or the Server object)."""
    events = Events()
    sub = await client.create_subscription(20, events)
    types = [client.get_node(TRANSITION), client.get_node(AUDIT)]
    await sub.subscribe_events(client.get_node(node), types)
    return events


async def call(client: Client, ns: int, obj: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    res = await raw_call(client, ua.NodeId(obj, ns), ua.NodeId(f"{obj}.{method}", ns), *args)
    assert res.StatusCode.is_good(), (method, res.StatusCode)
    return res


def pairs(events: Events) -> list[tuple[str, str | None]]:
    """(transition, user) for every TransitionEvent of one machine: the ClientUserId of the audit event
    right after it with the same states (ANONYMOUS when null), None without one."""
    out = []
    seq = events.events
    for i, e in enumerate(seq):
        if e.EventType != TRANSITION:
            continue
        audit = seq[i + 1] if i + 1 < len(seq) else None
        matched = (
            audit is not None
            and audit.EventType == AUDIT
            and audit.OldStateId == getattr(e, "FromState/Id")
            and audit.NewStateId == getattr(e, "ToState/Id")
        )
        out.append((e.Transition.Text, (audit.ClientUserId or ANONYMOUS) if matched and audit is not None else None))
    return out


async def test_a_users_packml_command_is_audited_and_so_is_the_acting_state_it_entered_completing(app) -> None:
    client, ns = await connect(app, "otto")
    try:
        machine = await watch(client, ua.NodeId(MACHINE, ns))
        execute = await watch(client, ua.NodeId(EXECUTE, ns))
        server = await watch(client, ua.NodeId(ua.ObjectIds.Server))
        before = datetime.now().astimezone()
        await call(client, ns, MACHINE, "Reset")
        await execute.wait_for(lambda e: e.Transition.Text == "ResettingToIdle" if e.EventType == TRANSITION else False)
        await delivered(app, machine, ua.NodeId(MACHINE, ns))
        await delivered(app, execute, ua.NodeId(EXECUTE, ns))
        assert pairs(machine) == [("StoppedToRunning", "otto")]
        # Resetting completed after the call returned: still otto's Reset (decision 38).
        assert pairs(execute) == [("ResettingToIdle", "otto")]
        (completed,) = execute.audits()
        assert (completed.SourceName, completed.MethodId) == ("Method/Reset", ua.NodeId(f"{MACHINE}.Reset", ns))
        (audit,) = machine.audits()
        (caused,) = machine.transitions()
        assert audit.SourceNode == ua.NodeId(MACHINE, ns)
        assert audit.SourceName == "Method/Reset"
        assert audit.MethodId == ua.NodeId(f"{MACHINE}.Reset", ns)
        assert audit.InputArguments == []
        assert audit.Status is True
        assert audit.ServerId == app.config.server.application_uri
        assert before <= audit.ActionTimeStamp <= audit.Time
        assert audit.OldStateId == getattr(caused, "FromState/Id") and audit.NewStateId == getattr(caused, "ToState/Id")
        assert "otto" in audit.Message.Text
        # The Server object's subscribers get it too, and the server says it audits.
        at_server = await server.wait_for(lambda e: e.EventType == AUDIT)
        assert (at_server.SourceNode, at_server.ClientUserId) == (ua.NodeId(MACHINE, ns), "otto")
        assert await client.get_node(ua.ObjectIds.Server_Auditing).read_value() is True
    finally:
        await client.disconnect()


async def test_a_start_with_parameters_carries_them_in_its_audit_event(app) -> None:
    client, ns = await connect(app, "otto")
    try:
        await client.load_data_type_definitions()
        unit = app.registry(UNITS)["Filler1"].unit
        if unit.state != "Idle":  # the first test leaves it there; otherwise bring it there
            await wait_until(lambda: unit.state in ("Stopped", "Idle"))
            if unit.state == "Stopped":
                await call(client, ns, MACHINE, "Reset")
            await wait_until(lambda: unit.state == "Idle")
        execute = await watch(client, ua.NodeId(EXECUTE, ns))
        parameter = ua.PackMLDescriptorDataType(ID=7, Name="FillVolume", Value=250.5)
        await call(client, ns, EXECUTE, "Start", ua.Variant([parameter], ua.VariantType.ExtensionObject))
        await execute.wait_for(lambda e: e.EventType == TRANSITION and e.Transition.Text == "StartingToExecute")
        await delivered(app, execute, ua.NodeId(EXECUTE, ns))
        assert pairs(execute) == [("IdleToStarting", "otto"), ("StartingToExecute", "otto")]
        audit, completed = execute.audits()
        assert completed.MethodId == audit.MethodId == ua.NodeId(f"{EXECUTE}.Start", ns)
        (argument,) = audit.InputArguments
        assert [(d.ID, d.Name, d.Value) for d in argument.Value] == [(7, "FillVolume", 250.5)]
        await call(client, ns, MACHINE, "Stop")
        await wait_until(lambda: unit.state == "Stopped")
    finally:
        await client.disconnect()


async def test_robot_calls_are_audited_for_their_caller_and_a_program_ending_by_itself_is_not(app) -> None:
    anonymous, ns = await connect(app)
    otto, _ = await connect(app, "otto")
    try:
        so, idle, tc = [await watch(otto, ua.NodeId(path, ns)) for path in (SO, f"{SO}.IdleSubstateMachine", TC)]
        # GetReady (anonymous): StandBy -> GettingReady is the call's, and so is Idle -> Ready once the
        # drives are on (decision 38).
        await call(anonymous, ns, SO, "GetReady")
        await so.wait_for(lambda e: e.EventType == TRANSITION)
        load = await call(otto, ns, TC, "LoadByName", ua.Variant("short", ua.VariantType.String))
        assert load.OutputArguments[0].Value == 0
        await call(otto, ns, TC, "Start")
        await tc.wait_for(lambda e: e.EventType == TRANSITION and e.Transition.Text == "ExecutingToReady")
        for events, path in ((so, SO), (idle, f"{SO}.IdleSubstateMachine"), (tc, TC)):
            await delivered(app, events, ua.NodeId(path, ns))
        assert pairs(idle)[0] == ("StandByToGettingReady", ANONYMOUS)
        assert pairs(so) == [
            ("IdleToReady", ANONYMOUS),  # the drives came on: GetReady completed
            ("ReadyToExecuting", "otto"),  # the task control's Start started the system (decision 19)
            ("ExecutingToReady", None),  # the program ended
        ]
        assert pairs(tc) == [("IdleToReady", "otto"), ("ReadyToExecuting", "otto"), ("ExecutingToReady", None)]
        anon = idle.audits()[0]
        assert anon.ClientUserId is None  # OPC 10000-5 6.4.3: null for an anonymous session
        assert (anon.SourceName, anon.MethodId) == ("Method/GetReady", ua.NodeId(f"{SO}.GetReady", ns))
        loaded, started = tc.audits()
        assert (loaded.SourceName, [v.Value for v in loaded.InputArguments]) == ("Method/LoadByName", ["short"])
        assert (started.SourceName, started.InputArguments) == ("Method/Start", [])
        powered_up, system_started = so.audits()
        assert (powered_up.ClientUserId, powered_up.MethodId) == (None, ua.NodeId(f"{SO}.GetReady", ns))
        assert system_started.MethodId == ua.NodeId(f"{TC}.Start", ns)
        await call(otto, ns, TC, "UnloadProgram")
        await call(otto, ns, SO, "StandDown")
    finally:
        await otto.disconnect()
        await anonymous.disconnect()


async def test_a_stop_and_a_stand_down_that_finish_after_the_call_are_the_callers(app) -> None:
    """TaskControl Stop answers at once and the run ends when the robot has stopped; StandDown answers
    at once and ReadyToIdle follows once the drives are off: both AuditUpdateStateEvents name the
    caller and the method (decision 38)."""
    otto, ns = await connect(app, "otto")
    try:
        so, tc = [await watch(otto, ua.NodeId(path, ns)) for path in (SO, TC)]
        await call(otto, ns, SO, "GetReady")
        await so.wait_for(lambda e: e.EventType == TRANSITION and e.Transition.Text == "IdleToReady")
        await call(otto, ns, TC, "LoadByName", ua.Variant("long", ua.VariantType.String))
        await call(otto, ns, TC, "Start")
        await tc.wait_for(lambda e: e.EventType == TRANSITION and e.Transition.Text == "ReadyToExecuting")
        await call(otto, ns, TC, "Stop", ua.Variant(4, ua.VariantType.Int64))  # QuickStop
        await tc.wait_for(lambda e: e.EventType == TRANSITION and e.Transition.Text == "ExecutingToReady")
        await call(otto, ns, TC, "UnloadProgram")
        await call(otto, ns, SO, "StandDown")
        await so.wait_for(lambda e: e.EventType == TRANSITION and e.Transition.Text == "ReadyToIdle")
        for events, path in ((so, SO), (tc, TC)):
            await delivered(app, events, ua.NodeId(path, ns))
        assert pairs(tc) == [
            ("IdleToReady", "otto"),
            ("ReadyToExecuting", "otto"),
            ("ExecutingToReady", "otto"),  # the robot stopped after Stop returned
            ("ReadyToIdle", "otto"),
        ]
        stopped = tc.audits()[2]
        assert (stopped.SourceName, stopped.MethodId) == ("Method/Stop", ua.NodeId(f"{TC}.Stop", ns))
        assert [v.Value for v in stopped.InputArguments] == [4]
        assert pairs(so)[-2:] == [("ExecutingToReady", "otto"), ("ReadyToIdle", "otto")]
        stood_down = so.audits()[-1]
        assert (stood_down.SourceName, stood_down.MethodId) == ("Method/StandDown", ua.NodeId(f"{SO}.StandDown", ns))
        assert stood_down.ActionTimeStamp <= stood_down.Time
    finally:
        await otto.disconnect()


async def test_background_tasks_do_not_inherit_the_spawners_context() -> None:
    var: contextvars.ContextVar[str] = contextvars.ContextVar("probe", default="none")
    seen: list[str] = []

    async def probe() -> None:
        seen.append(var.get())

    bg = Background()
    token = var.set("the caller")
    try:
        bg.spawn(probe())
    finally:
        var.reset(token)
    await wait_until(lambda: bool(seen))
    await bg.close()
    assert seen == ["none"]
