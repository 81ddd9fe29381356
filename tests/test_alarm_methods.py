"""Alarm AddComment, Enable and Disable (OPC 10000-9 ConditionType): the model, then through asyncua.

Roles follow the one role table: operators comment, engineers enable and disable.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import time
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import robotics_tables, simulated_robot

from uacell.core.errors import CallError
from uacell.core.roles import Role
from uacell.robotics.model import RobotCell, Status
from uacell.robotics.program_cache import DirectoryLibrary
from uacell.robotics.sim import SimulatedRobot

COND = "Robot1.Controllers.Controller1.SystemOperation.Conditions.EmergencyStop"
SO = "Robot1.Controllers.Controller1.SystemOperation.SystemOperationStateMachine"
TC = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
TIMEOUT = 30.0


# --- the model ---------------------------------------------------------------------------------------------


async def test_model_enable_disable_and_comment(tmp_path: Path) -> None:
    cell = RobotCell(SimulatedRobot(time_scale=20.0), DirectoryLibrary(tmp_path), tables=robotics_tables())
    try:
        so = cell.system
        seen: list[tuple[bool, str]] = []
        so.condition_listeners.append(lambda c: seen.append((c.enabled, c.comment)))
        cell.equipment.raise_alarm("EmergencyStop")  # type: ignore[attr-defined]
        assert so.alarm_status() == Status.E_ACTIVE_ALARM
        so.add_comment("EmergencyStop", "technician on the way")
        assert so.conditions["EmergencyStop"].comment == "technician on the way"
        with pytest.raises(CallError) as err:
            so.set_enabled("EmergencyStop", True)
        assert err.value.status == "BadConditionAlreadyEnabled"
        so.set_enabled("EmergencyStop", False)
        assert so.alarm_status() is None  # a disabled condition is not evaluated
        for call in (lambda: so.acknowledge("EmergencyStop"), lambda: so.add_comment("EmergencyStop", "x")):
            with pytest.raises(CallError) as err:
                call()
            assert err.value.status == "BadConditionDisabled"
        with pytest.raises(CallError) as err:
            so.set_enabled("EmergencyStop", False)
        assert err.value.status == "BadConditionAlreadyDisabled"
        so.set_enabled("EmergencyStop", True)
        assert so.alarm_status() == Status.E_ACTIVE_ALARM  # evaluated again
        assert seen[-3:] == [(True, "technician on the way"), (False, "technician on the way"),
                             (True, "technician on the way")]  # fmt: skip
        with pytest.raises(CallError) as err:
            so.set_enabled("Nope", True)
        assert err.value.status == "BadNodeIdUnknown"
    finally:
        await cell.close()


# --- through asyncua -------------------------------------------------------------------------------------


class Events:
    def __init__(self) -> None:
        self.items: list[Any] = []

    def event_notification(self, event) -> None:
        self.items.append(event)

    async def wait_for(self, predicate, timeout: float = TIMEOUT):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for ev in self.items:
                if predicate(ev):
                    return ev
            await asyncio.sleep(0.02)
        raise AssertionError(f"no such event among {len(self.items)}")


@pytest.fixture
async def rig(tmp_path):
    app = await start_app(fast_config(tmp_path / "data"))
    client = Client(app.endpoint, timeout=30)
    await client.connect()
    try:
        yield app, client
    finally:
        await client.disconnect()
        await app.stop()


def nid(app, path: str) -> ua.NodeId:
    return ua.NodeId(path, app.cell.instantiator.ns)


async def call(client: Client, obj: ua.NodeId, method: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
    req = ua.CallMethodRequest(ObjectId=obj, MethodId=method, InputArguments=list(args))
    (res,) = await client.uaclient.call([req])
    return res


async def as_role(app, role: Role):
    """A new anonymous client that gets ``role`` (the listening policy's anonymous role, changed for the test)."""
    manager = app.server.iserver.user_manager
    policy = manager.policy
    manager.policy = dataclasses.replace(policy, anonymous_role=role)
    client = Client(app.endpoint, timeout=30)
    try:
        await client.connect()
    finally:
        manager.policy = policy
    return client


async def test_add_comment_enable_disable_through_asyncua(rig):
    app, client = rig
    cond = nid(app, COND)
    methods = {name: app.dispatcher.method_of(cond, name) for name in ("AddComment", "Enable", "Disable")}
    events = Events()
    sub = await client.create_subscription(20, events)
    await sub.subscribe_events(client.get_node(ua.ObjectIds.Server), client.get_node(ua.ObjectIds.AlarmConditionType))
    simulated_robot(app).raise_alarm("EmergencyStop")
    await app.settle()
    read = lambda p: client.get_node(nid(app, f"{COND}.{p}")).read_value()  # noqa: E731
    event_id = await read("EventId")
    text = ua.Variant(ua.LocalizedText("technician on the way"), ua.VariantType.LocalizedText)

    # AddComment (operator): unknown EventId, then the current one
    res = await call(client, cond, methods["AddComment"], ua.Variant(b"nope", ua.VariantType.ByteString), text)
    assert res.StatusCode.value == ua.StatusCodes.BadEventIdUnknown
    assert [r.value for r in res.InputArgumentResults] == [ua.StatusCodes.BadEventIdUnknown, ua.StatusCodes.Good]
    res = await call(client, cond, methods["AddComment"], ua.Variant(event_id, ua.VariantType.ByteString), text)
    assert res.StatusCode.is_good(), res.StatusCode
    await app.settle()
    assert (await read("Comment")).Text == "technician on the way"
    assert await read("ClientUserId") == "anonymous"
    ev = await events.wait_for(
        lambda e: getattr(e, "Comment", None) is not None and e.Comment.Text == "technician on the way"
    )
    assert ev.ConditionName == "EmergencyStop" and ev.EventId != event_id

    # Enable and Disable need an engineer
    res = await call(client, cond, methods["Disable"])
    assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    assert await read("EnabledState.Id") is True
    engineer = await as_role(app, Role.ENGINEER)
    try:
        assert await engineer.get_node(methods["Disable"]).read_attribute(ua.AttributeIds.UserExecutable)
        res = await call(engineer, cond, methods["Disable"])
        assert res.StatusCode.is_good(), res.StatusCode
        await app.settle()
        assert await read("EnabledState.Id") is False
        assert (await read("EnabledState")).Text == "Disabled"
        assert await read("Retain") is False
        await events.wait_for(lambda e: getattr(e, "EnabledState/Id", None) is False and e.Retain is False)
        res = await call(engineer, cond, methods["Disable"])
        assert res.StatusCode.value == ua.StatusCodes.BadConditionAlreadyDisabled
        # while disabled: not acknowledgeable, not commentable, and GetReady is not refused for it
        res = await call(
            client, cond, methods["AddComment"], ua.Variant(await read("EventId"), ua.VariantType.ByteString), text
        )
        assert res.StatusCode.value == ua.StatusCodes.BadConditionDisabled
        get_ready = app.dispatcher.method_of(nid(app, SO), "GetReady")
        res = await call(client, nid(app, SO), get_ready)
        assert res.OutputArguments[0].Value != int(Status.E_ACTIVE_ALARM)
        res = await call(engineer, cond, methods["Enable"])
        assert res.StatusCode.is_good(), res.StatusCode
        await app.settle()
        assert await read("EnabledState.Id") is True and await read("Retain") is True  # still active
        await events.wait_for(lambda e: getattr(e, "EnabledState/Id", None) is True and e.Retain is True)
        res = await call(engineer, cond, methods["Enable"])
        assert res.StatusCode.value == ua.StatusCodes.BadConditionAlreadyEnabled
    finally:
        await engineer.disconnect()
    # observers may not comment
    observer = await as_role(app, Role.OBSERVER)
    try:
        res = await call(
            observer, cond, methods["AddComment"], ua.Variant(await read("EventId"), ua.VariantType.ByteString), text
        )
        assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    finally:
        await observer.disconnect()
    await sub.delete()


@pytest.mark.interop
async def test_node_opcua_comments_disables_and_enables_an_alarm(tmp_path):
    from conftest import run_node

    config = fast_config(tmp_path / "data")
    config.server.anonymous_role = "engineer"  # Enable/Disable are an engineer's
    app = await start_app(config)
    try:
        simulated_robot(app).raise_alarm("EmergencyStop")
        await app.settle()
        out = await asyncio.to_thread(run_node, "alarms.js", app.endpoint)
    finally:
        await app.stop()
    assert out == {
        "addCommentUnknown": "BadEventIdUnknown",
        "addComment": "Good",
        "comment": "from node-opcua",
        "disable": "Good",
        "enabledAfterDisable": False,
        "disableAgain": "BadConditionAlreadyDisabled",
        "addCommentDisabled": "BadConditionDisabled",
        "enable": "Good",
        "enabledAfterEnable": True,
        "enableAgain": "BadConditionAlreadyEnabled",
    }


async def test_executable_of_a_robot_condition_follows_the_condition(rig):
    """Executable of a robot condition's methods changes with the condition: raised by the equipment
    (outside any call), acknowledged, disabled. Waited for with the publisher alone (``settle`` would
    re-evaluate every method): what the change itself touched."""
    app, client = rig
    cond = nid(app, COND)
    names = ("Acknowledge", "AddComment", "Enable", "Disable")

    async def executable() -> dict[str, bool]:
        result = {}
        for name in names:
            dv = await client.get_node(app.dispatcher.method_of(cond, name)).read_attribute(ua.AttributeIds.Executable)
            result[name] = dv.Value.Value
        return result

    quiet = {"Acknowledge": False, "AddComment": True, "Enable": False, "Disable": True}
    assert await executable() == quiet
    simulated_robot(app).raise_alarm("EmergencyStop")
    await app.publisher.flush()
    assert await executable() == {**quiet, "Acknowledge": True}
    event_id = await client.get_node(nid(app, f"{COND}.EventId")).read_value()
    comment = ua.Variant(ua.LocalizedText("seen"), ua.VariantType.LocalizedText)
    res = await call(client, cond, app.dispatcher.method_of(cond, "Acknowledge"), ua.Variant(event_id), comment)
    assert res.StatusCode.is_good(), res.StatusCode
    await app.publisher.flush()
    assert await executable() == quiet
    simulated_robot(app).raise_alarm("EmergencyStop")
    await app.publisher.flush()
    engineer = await as_role(app, Role.ENGINEER)
    try:
        res = await call(engineer, cond, app.dispatcher.method_of(cond, "Disable"))
        assert res.StatusCode.is_good(), res.StatusCode
        await app.publisher.flush()
        assert await executable() == {"Acknowledge": False, "AddComment": False, "Enable": True, "Disable": False}
    finally:
        await engineer.disconnect()


async def test_a_task_control_call_leaves_executable_of_the_conditions_alone(rig):
    """A program load changes the task control, not a condition: the conditions' methods are not
    re-evaluated for it (their own scope), the task control's are."""
    app, client = rig
    evaluated: list[str] = []
    for method_id, bound in app.dispatcher.methods.items():
        if bound.executable is not None and str(method_id.Identifier).startswith("Robot1."):  # not the filler's
            bound.executable = functools.partial(_counted, evaluated, bound.name, bound.executable)
    await app.settle()
    evaluated.clear()
    tc = nid(app, TC)
    res = await call(
        client, tc, app.dispatcher.method_of(tc, "LoadByName"), ua.Variant("pick_and_place", ua.VariantType.String)
    )
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0, res
    await app.publisher.flush()  # what the call changed, with Executable of the scopes it touched
    assert "UnloadProgram" in evaluated and "Start" in evaluated
    assert not {"Acknowledge", "AddComment", "Enable", "Disable"} & set(evaluated), evaluated


def _counted(evaluated: list[str], name: str, executable: Any) -> bool:
    evaluated.append(name)
    return bool(executable())
