"""The state-machine binding and the method dispatcher, through a real asyncua client over TCP.

A test binder drives TaskControl1's machines directly (the Robotics issue adds real behaviour), so
these tests exercise only the shared machinery: published state, events, Bad_StateNotActive,
argument checks, roles and the no-exception-escapes rule.
"""

from __future__ import annotations

import asyncio
import dataclasses
from typing import Any

import pytest
from asyncua import Client, Node, ua
from conftest import fast_config, start_app
from helpers import official, raw_call, wait_until

from uacell.binding.machine_binding import bind_tree
from uacell.core.errors import CallError
from uacell.core.fsm import Reason, StateMachine
from uacell.core.roles import Family, Role
from uacell.host import ServerView
from uacell.models import fsm_table
from uacell.robotics.companion import TASK_CONTROL
from uacell.server import UacellServer

ROB = "http://opcfoundation.org/UA/Robotics/"
TC_PATH = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"


class Rig:
    """What the test binder made, so tests can drive it."""

    machine: StateMachine
    ready: StateMachine
    calls: list[Any]
    # set by the rig fixture
    app: UacellServer
    client: Client
    ns: int
    rob: int
    tc: Node


async def _test_binder(app: ServerView, rig: Rig):
    ns = app.cell.instantiator.ns
    node = ua.NodeId(TC_PATH, ns)
    rig.machine = StateMachine(
        "TaskControlStateMachine", fsm_table(official(), "Robotics", "TaskControlStateMachineType"), "Idle"
    )
    rig.ready = StateMachine(
        "ReadySubstateMachine",
        fsm_table(official(), "Robotics", "ReadySubstateMachineType"),
        "AtProgramStart",
        parent=rig.machine,
        parent_state="Ready",
    )
    rig.calls = []
    await bind_tree(app.server, node, rig.machine, app.publisher)
    d = app.dispatcher

    async def load_by_name(caller, name):
        rig.calls.append((caller.role, name))
        if name == "boom":
            raise RuntimeError("behaviour bug")
        if name == "bad":
            raise CallError("BadInvalidArgument", "bad name", argument=0)
        if rig.machine.current == "Idle":
            rig.machine.take("IdleToReady", Reason.EXTERNAL)
            rig.ready.enter("AtProgramStart")
            return [0]
        return [1]

    async def load_by_node_id(caller, node_id):
        return [0]

    async def stop(caller, mode):
        rig.calls.append(("stop", mode))
        return [0]

    d.bind(
        node,
        d.method_of(node, "LoadByName"),
        TASK_CONTROL,
        load_by_name,
        executable=lambda: rig.machine.current in ("Idle", "Ready"),
        serialize_on=rig.machine,
    )
    d.bind(node, d.method_of(node, "LoadByNodeId"), TASK_CONTROL, load_by_node_id)
    d.bind(
        node,
        d.method_of(node, "Stop"),
        TASK_CONTROL,
        stop,
        executable=lambda: rig.machine.current == "Executing",
    )
    return None


@pytest.fixture
async def rig(tmp_path):
    r = Rig()
    app = await start_app(fast_config(tmp_path / "data"), [lambda a: _test_binder(a, r)])
    client = Client(app.endpoint, timeout=30)
    await client.connect()
    r.app, r.client = app, client
    r.ns = await client.get_namespace_index("urn:uacell:cell")
    r.rob = await client.get_namespace_index(ROB)
    r.tc = client.get_node(ua.NodeId(TC_PATH, r.ns))
    try:
        yield r
    finally:
        await client.disconnect()
        await app.stop()


def node(r: Rig, *path: str):
    return r.client.get_node(ua.NodeId(".".join((TC_PATH, *path)), r.ns))


async def call(r: Rig, method: str, *args: ua.Variant, on=None) -> ua.CallMethodResult:
    return await raw_call(r.client, on or r.tc.nodeid, ua.NodeId(f"{TC_PATH}.{method}", r.ns), *args)


async def test_current_state_and_last_transition_after_a_transition(rig):
    r = rig
    assert (await node(r, "CurrentState").read_value()).Text == "Idle"
    assert await node(r, "CurrentState", "Id").read_value() == ua.NodeId(5040, r.rob)
    assert await node(r, "CurrentState", "Number").read_value() == 1
    res = await call(r, "LoadByName", ua.Variant("prog", ua.VariantType.String))
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0
    assert res.OutputArguments[0].VariantType == ua.VariantType.Int32
    assert (await node(r, "CurrentState").read_value()).Text == "Ready"
    assert await node(r, "CurrentState", "Id").read_value() == ua.NodeId(5041, r.rob)
    assert await node(r, "CurrentState", "Number").read_value() == 2
    assert (await node(r, "LastTransition").read_value()).Text == "IdleToReady"
    assert await node(r, "LastTransition", "Id").read_value() == ua.NodeId(5044, r.rob)
    assert await node(r, "LastTransition", "Number").read_value() == 2
    assert await node(r, "LastTransition", "TransitionTime").read_value() is not None
    assert await node(r, "LastTransitionReason").read_value() == 1
    states = await node(r, "AvailableStates").read_value()
    assert states == [ua.NodeId(5040, r.rob), ua.NodeId(5041, r.rob), ua.NodeId(5042, r.rob)]


class _Collector:
    def __init__(self):
        self.events = []
        self.arrived = asyncio.Event()

    def event_notification(self, event):
        self.events.append(event)
        self.arrived.set()


@pytest.mark.parametrize("source", ["machine", "server"])
async def test_subscription_receives_the_transition_event(rig, source):
    r = rig
    handler = _Collector()
    sub = await r.client.create_subscription(50, handler)
    target = r.tc if source == "machine" else r.client.get_node(ua.ObjectIds.Server)
    evtype = r.client.get_node(ua.ObjectIds.TransitionEventType)
    await sub.subscribe_events(target, evtype)  # active once the server has answered
    res = await call(r, "LoadByName", ua.Variant("prog", ua.VariantType.String))
    assert res.StatusCode.is_good()
    await asyncio.wait_for(handler.arrived.wait(), 10)
    ev = handler.events[0]
    assert ev.SourceNode == r.tc.nodeid
    assert ev.Transition.Text == "IdleToReady"
    assert getattr(ev, "Transition/Id") == ua.NodeId(5044, r.rob)
    assert ev.FromState.Text == "Idle" and getattr(ev, "FromState/Id") == ua.NodeId(5040, r.rob)
    assert ev.ToState.Text == "Ready" and getattr(ev, "ToState/Id") == ua.NodeId(5041, r.rob)
    assert "IdleToReady" in ev.Message.Text
    await sub.delete()


async def test_sub_machine_reads_bad_state_not_active_until_parent_state_entered(rig):
    r = rig
    for path in (
        ("ReadySubstateMachine", "CurrentState"),
        ("ReadySubstateMachine", "CurrentState", "Id"),
        ("ReadySubstateMachine", "LastTransition"),
        ("ReadySubstateMachine", "LastTransition", "Id"),
    ):
        dv = await node(r, *path).read_data_value(raise_on_bad_status=False)
        assert dv.StatusCode.value == ua.StatusCodes.BadStateNotActive, path
    await call(r, "LoadByName", ua.Variant("prog", ua.VariantType.String))
    dv = await node(r, "ReadySubstateMachine", "CurrentState").read_data_value()
    assert dv.StatusCode.is_good() and dv.Value.Value.Text == "AtProgramStart"
    assert await node(r, "ReadySubstateMachine", "CurrentState", "Id").read_value() == ua.NodeId(5023, r.rob)


async def test_argument_errors_have_precise_codes_and_argument_results(rig):
    r = rig
    res = await call(r, "LoadByName")
    assert res.StatusCode.value == ua.StatusCodes.BadArgumentsMissing
    res = await call(r, "LoadByName", ua.Variant("a", ua.VariantType.String), ua.Variant("b", ua.VariantType.String))
    assert res.StatusCode.value == ua.StatusCodes.BadTooManyArguments
    res = await call(r, "LoadByName", ua.Variant(5, ua.VariantType.Int32))
    assert res.StatusCode.value == ua.StatusCodes.BadTypeMismatch
    assert [c.value for c in res.InputArgumentResults] == [ua.StatusCodes.BadTypeMismatch]
    res = await call(r, "LoadByNodeId", ua.Variant("x", ua.VariantType.String))
    assert res.StatusCode.value == ua.StatusCodes.BadTypeMismatch
    res = await call(r, "Stop", ua.Variant(2, ua.VariantType.Int32))  # StopMode is Int64
    assert res.StatusCode.value == ua.StatusCodes.BadTypeMismatch
    res = await call(r, "Stop", ua.Variant(2, ua.VariantType.Int64))
    assert res.StatusCode.is_good()
    res = await call(r, "LoadByName", ua.Variant("bad", ua.VariantType.String))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert [c.value for c in res.InputArgumentResults] == [ua.StatusCodes.BadInvalidArgument]
    # nothing changed
    assert (await node(r, "CurrentState").read_value()).Text == "Idle"


async def test_method_on_wrong_object_is_method_invalid(rig):
    r = rig
    other = r.client.get_node(ua.ObjectIds.Server).nodeid
    res = await call(r, "LoadByName", ua.Variant("p", ua.VariantType.String), on=other)
    assert res.StatusCode.value == ua.StatusCodes.BadMethodInvalid
    res = await call(r, "LoadByName", ua.Variant("p", ua.VariantType.String), on=ua.NodeId("nope", r.ns))
    assert res.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown


async def test_exception_in_behaviour_is_internal_error_and_server_keeps_serving(rig):
    r = rig
    res = await call(r, "LoadByName", ua.Variant("boom", ua.VariantType.String))
    assert res.StatusCode.value == ua.StatusCodes.BadInternalError
    res = await call(r, "LoadByName", ua.Variant("prog", ua.VariantType.String))
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0


async def test_executable_follows_state(rig):
    r = rig
    load = node(r, "LoadByName")
    stop = node(r, "Stop")
    assert (await load.read_attribute(ua.AttributeIds.Executable)).Value.Value is True
    assert (await stop.read_attribute(ua.AttributeIds.Executable)).Value.Value is False


async def test_observer_gets_user_access_denied_and_nothing_changes(rig):
    r = rig
    # anonymous as on a plant network
    manager = r.app.server.iserver.user_manager
    manager.policy = dataclasses.replace(manager.policy, anonymous_role=Role.OBSERVER)
    observer = Client(r.app.endpoint, timeout=30)
    await observer.connect()
    try:
        res = await raw_call(
            observer, r.tc.nodeid, ua.NodeId(f"{TC_PATH}.LoadByName", r.ns), ua.Variant("prog", ua.VariantType.String)
        )
        assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    finally:
        await observer.disconnect()
    assert (await node(r, "CurrentState").read_value()).Text == "Idle"
    assert r.calls == []


async def test_executable_follows_changes_made_outside_method_calls(rig):
    """Decision 4 when no call is involved (an acting state completing, a program ending)."""
    r = rig
    stop = node(r, "Stop")
    r.machine.take("IdleToReady", Reason.SYSTEM)
    r.machine.take("ReadyToExecuting", Reason.SYSTEM)
    for _ in range(100):
        if (await stop.read_attribute(ua.AttributeIds.Executable)).Value.Value is True:
            break
        await asyncio.sleep(0.05)
    assert (await stop.read_attribute(ua.AttributeIds.Executable)).Value.Value is True
    assert (await node(r, "LoadByName").read_attribute(ua.AttributeIds.Executable)).Value.Value is False


async def test_methods_no_binding_declares_never_get_the_stacks_default_answers(rig):
    r = rig
    server_obj = ua.NodeId(ua.ObjectIds.Server)
    get_monitored = ua.NodeId(ua.ObjectIds.Server_GetMonitoredItems)
    one = ua.Variant(1, ua.VariantType.UInt32)
    # another object's method, called on the task control: not its method
    res = await raw_call(r.client, r.tc.nodeid, get_monitored, one)
    assert res.StatusCode.value == ua.StatusCodes.BadMethodInvalid
    # a node that is not a method at all
    res = await raw_call(r.client, r.tc.nodeid, ua.NodeId(f"{TC_PATH}.CurrentState", r.ns))
    assert res.StatusCode.value == ua.StatusCodes.BadMethodInvalid
    # the object's own method that nobody implements (the rig binds no Start; asyncua no SetSubscriptionDurable)
    res = await raw_call(r.client, r.tc.nodeid, ua.NodeId(f"{TC_PATH}.Start", r.ns))
    assert res.StatusCode.value == ua.StatusCodes.BadNotImplemented
    durable = ua.NodeId(ua.ObjectIds.Server_SetSubscriptionDurable)
    res = await raw_call(r.client, server_obj, durable, one, one)
    assert res.StatusCode.value == ua.StatusCodes.BadNotImplemented
    # GetMonitoredItems is uacell's own (tests/test_diagnostics.py): it checks the subscription id
    res = await raw_call(r.client, server_obj, get_monitored, ua.Variant(987654, ua.VariantType.UInt32))
    assert res.StatusCode.value == ua.StatusCodes.BadSubscriptionIdInvalid
    assert r.calls == []


async def test_condition_refresh_is_open_to_alarm_clients(rig):
    """Alarm clients call ConditionType.ConditionRefresh when they subscribe; asyncua implements it."""
    r = rig
    condition_type = ua.NodeId(ua.ObjectIds.ConditionType)
    refresh = ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh)
    res = await raw_call(r.client, condition_type, refresh, ua.Variant(999999, ua.VariantType.UInt32))
    assert res.StatusCode.value == ua.StatusCodes.BadSubscriptionIdInvalid  # it ran: the id is checked
    sub = await r.client.create_subscription(100, _Collector())
    res = await raw_call(r.client, condition_type, refresh, ua.Variant(sub.subscription_id, ua.VariantType.UInt32))
    assert res.StatusCode.is_good(), res.StatusCode
    await sub.delete()


async def test_a_callback_method_outside_the_role_table_is_admin_only_and_never_raises(rig):
    from uacell.ua.context import INTERNAL

    r = rig
    ran = []

    async def boom(parent):
        ran.append(parent)
        raise RuntimeError("bug in a plain asyncua callback")

    method = await r.app.server.get_node(r.tc.nodeid).add_method(
        ua.NodeId("Test.Boom", r.ns), ua.QualifiedName("Boom", r.ns), boom, [], []
    )
    res = await raw_call(r.client, r.tc.nodeid, method.nodeid)  # anonymous operator
    assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    assert ran == []
    req = ua.CallMethodRequest(ObjectId=r.tc.nodeid, MethodId=method.nodeid, InputArguments=[])
    res = await r.app.dispatcher.dispatch(req, INTERNAL)  # admin
    assert res.StatusCode.value == ua.StatusCodes.BadInternalError and ran == [r.tc.nodeid]
    res = await call(r, "LoadByName", ua.Variant("prog", ua.VariantType.String))
    assert res.StatusCode.is_good()


async def test_calls_during_shutdown_finish_and_later_ones_answer_bad_shutdown(rig):
    r = rig
    d = r.app.dispatcher
    gate = asyncio.Event()
    node_id = ua.NodeId(TC_PATH, r.ns)
    original = d.methods[d.method_of(node_id, "LoadByNodeId")].handler
    order: list[str] = []

    async def slow(caller, node_id):
        await gate.wait()
        order.append("call finished")
        return [0]

    d.methods[d.method_of(node_id, "LoadByNodeId")].handler = slow
    running = asyncio.create_task(call(r, "LoadByNodeId", ua.Variant(ua.NodeId(1), ua.VariantType.ExpandedNodeId)))
    await wait_until(lambda: d._running > 0)

    async def close() -> None:
        await d.close(timeout=10)
        order.append("closed")

    closing = asyncio.create_task(close())
    await wait_until(lambda: d._closing)  # close has begun
    req = ua.CallMethodRequest(
        ObjectId=node_id, MethodId=d.method_of(node_id, "LoadByName"), InputArguments=[ua.Variant("prog")]
    )
    late = await d.dispatch(req)  # asyncua answers one connection's requests in turn: call directly
    assert late.StatusCode.value == ua.StatusCodes.BadShutdown
    assert not closing.done()
    gate.set()
    assert (await running).StatusCode.is_good()
    await closing
    assert order == ["call finished", "closed"]  # close waited for the call under way
    d.methods[d.method_of(node_id, "LoadByNodeId")].handler = original


def test_unbinding_drops_the_methods_own_serialization_lock():
    from uacell.binding.dispatch import BoundMethod, MethodDispatcher

    d = MethodDispatcher.__new__(MethodDispatcher)
    d.methods, d._locks, d._scoped = {}, {}, {}
    # no handler: the method is only unbound, never called
    bound = BoundMethod(ua.NodeId(1), ua.NodeId(2), "M", Family.FILE, None, [], [])  # type: ignore[arg-type]
    d.methods[bound.method_id] = bound
    d._locks[id(bound)] = asyncio.Lock()
    d.unbind(bound.method_id)
    assert d._locks == {} and d.methods == {}


async def _call_with_diagnostics(r: Rig, mask: int, *args: ua.Variant) -> ua.CallMethodResult:
    from asyncua.ua.ua_binary import struct_from_binary

    req = ua.CallMethodRequest()
    req.ObjectId = r.tc.nodeid
    req.MethodId = ua.NodeId(f"{TC_PATH}.LoadByName", r.ns)
    req.InputArguments = list(args)
    request = ua.CallRequest()
    request.Parameters.MethodsToCall = [req]
    request.RequestHeader.ReturnDiagnostics = mask
    data = await r.client.uaclient.protocol.send_request(request)
    response = struct_from_binary(ua.CallResponse, data)
    (result,) = response.Results
    return result


async def test_argument_problems_come_with_diagnostics_when_the_client_asks(rig):
    r = rig
    bad = ua.Variant("bad", ua.VariantType.String)
    asked = await _call_with_diagnostics(r, 0x80, bad)  # operation-level AdditionalInfo
    assert asked.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert [i.AdditionalInfo for i in asked.InputArgumentDiagnosticInfos] == ["bad name"]
    not_asked = await _call_with_diagnostics(r, 0, bad)
    assert not_asked.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert not_asked.InputArgumentDiagnosticInfos == []


async def test_a_handler_may_use_asyncio_timeout_before_its_first_wait(rig):
    """Calls run eagerly (uacell.core.background.eager): before its first wait a handler is in a task all
    the same, so ``asyncio.timeout`` works there; one that expires gives the status the handler says."""
    r = rig
    d = r.app.dispatcher
    bound = d.methods[d.method_of(ua.NodeId(TC_PATH, r.ns), "LoadByNodeId")]
    original = bound.handler
    never: asyncio.Event = asyncio.Event()
    seen: list[object] = []

    async def quick(caller, node_id):
        seen.append(asyncio.current_task() is not None)
        async with asyncio.timeout(5):  # before any wait
            return [7]

    async def stuck(caller, node_id):
        try:
            async with asyncio.timeout(0.05):  # entered before the first wait, expires in it
                await never.wait()
        except TimeoutError:
            raise CallError("BadTimeout", "the equipment did not answer") from None
        return [0]

    arg = ua.Variant(ua.NodeId(1), ua.VariantType.ExpandedNodeId)
    try:
        bound.handler = quick
        res = await call(r, "LoadByNodeId", arg)
        assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 7 and seen == [True]
        bound.handler = stuck
        res = await call(r, "LoadByNodeId", arg)
        assert res.StatusCode.value == ua.StatusCodes.BadTimeout
        res = await call(r, "LoadByName", ua.Variant("prog", ua.VariantType.String))  # the connection goes on
        assert res.StatusCode.is_good()
    finally:
        bound.handler = original


async def test_the_quick_argument_check_agrees_with_the_full_one(rig):
    """``TypeChecker.accepts`` tells plain scalars at once: for every argument shape and value it must
    answer what the full ``check`` answers (the dispatcher refuses with the full check's codes)."""
    types = rig.app.dispatcher.types
    vt = ua.VariantType
    arguments = [
        ua.Argument(DataType=ua.NodeId(datatype), ValueRank=rank)
        for datatype in (
            ua.ObjectIds.Float, ua.ObjectIds.Int32, ua.ObjectIds.String, ua.ObjectIds.NodeId, ua.ObjectIds.Boolean,
            ua.ObjectIds.Duration,  # a subtype of Double
            ua.ObjectIds.Number, ua.ObjectIds.UInteger, ua.ObjectIds.BaseDataType, ua.ObjectIds.Enumeration,
            ua.ObjectIds.Argument,  # a structure
        )
        for rank in (-1, -2, -3, 0, 1)
    ]  # fmt: skip
    variants = [
        ua.Variant(1.5, vt.Float), ua.Variant(1.5, vt.Double), ua.Variant(3, vt.Int32), ua.Variant(3, vt.UInt16),
        ua.Variant("x", vt.String), ua.Variant(None, vt.String), ua.Variant(True, vt.Boolean),
        ua.Variant(ua.NodeId(5), vt.NodeId), ua.Variant(None, vt.Null), ua.Variant([1.5, 2.5], vt.Float),
        ua.Variant([], vt.Int32), ua.Variant(ua.Argument(), vt.ExtensionObject),
        ua.Variant(ua.EUInformation(), vt.ExtensionObject),
    ]  # fmt: skip
    told = {(a.DataType.Identifier, a.ValueRank, v.VariantType, repr(v.Value)): types.accepts(v, a)
            for a in arguments for v in variants}  # fmt: skip
    full = {(a.DataType.Identifier, a.ValueRank, v.VariantType, repr(v.Value)): types.check(v, a).is_good()
            for a in arguments for v in variants}  # fmt: skip
    assert told == full
    assert told[(ua.ObjectIds.Float, -1, vt.Float, "1.5")] and not told[(ua.ObjectIds.Float, -1, vt.Double, "1.5")]
    assert told[(ua.ObjectIds.Duration, -1, vt.Double, "1.5")] and not told[(ua.ObjectIds.Int32, -1, vt.Null, "None")]
    # asked twice (the second time from what the first one kept): the same answers
    assert {k: types.accepts(v, a) for a in arguments for v in variants
            for k in [(a.DataType.Identifier, a.ValueRank, v.VariantType, repr(v.Value))]} == full  # fmt: skip
