"""Filler1 (PackML) through a real asyncua client over TCP: the TR88 walk with its events, every Start
error, unit modes, speeds, production counters, Status/StartParameters, InjectFault, and Admin data
surviving a restart."""

from __future__ import annotations

import asyncio
import math
import time
import uuid
from pathlib import Path

from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import fire_marker, official, raw_call, wait_until

from uacell.models import fsm_table
from uacell.packml.binding import UNITS
from uacell.server import UacellServer

CELL = "urn:uacell:cell"
PACKML = "http://opcfoundation.org/UA/PackML/"
F = "Filler1"
BASE = f"{F}.BaseStateMachine"
MACH = f"{BASE}.MachineState"
EXEC = f"{MACH}.ExecuteState"
MACHINES = {"Base": BASE, "Machine": MACH, "Execute": EXEC}
TYPES = {
    "Base": "PackMLBaseStateMachineType",
    "Machine": "PackMLMachineStateMachineType",
    "Execute": "PackMLExecuteStateMachineType",
}
# TR88 state numbers (docs/packml.md), checked against CurrentState/Number.
NUMBERS = {
    "Clearing": 1,
    "Stopped": 2,
    "Starting": 3,
    "Idle": 4,
    "Suspended": 5,
    "Execute": 6,
    "Stopping": 7,
    "Aborting": 8,
    "Aborted": 9,
    "Holding": 10,
    "Held": 11,
    "Unholding": 12,
    "Suspending": 13,
    "Unsuspending": 14,
    "Resetting": 15,
    "Completing": 16,
    "Complete": 17,
    "Running": 18,
    "Cleared": 19,
}
TIMEOUT = 10.0


class Unit:
    """Client-side helpers for Filler1."""

    def __init__(self, client: Client, ns: int, pml: int) -> None:
        self.client, self.ns, self.pml = client, ns, pml
        self.tables = {k: fsm_table(official(), "PackML", t) for k, t in TYPES.items()}

    def node(self, path: str):
        return self.client.get_node(ua.NodeId(path, self.ns))

    async def value(self, path: str):
        return await self.node(f"{F}.{path}").read_value()

    async def call(self, obj: str, method: str, *args: ua.Variant, obj_id: ua.NodeId | None = None):
        method_id = ua.NodeId(f"{obj}.{method}", self.ns)
        return await raw_call(self.client, obj_id or ua.NodeId(obj, self.ns), method_id, *args)

    async def ok(self, obj: str, method: str, *args: ua.Variant) -> None:
        res = await self.call(obj, method, *args)
        assert res.StatusCode.is_good(), (method, res.StatusCode)

    async def current(self, machine: str) -> str | None:
        """The machine's CurrentState text, None when it reads Bad_StateNotActive."""
        dv = await self.node(f"{MACHINES[machine]}.CurrentState").read_data_value(raise_on_bad_status=False)
        if dv.StatusCode.value == ua.StatusCodes.BadStateNotActive:
            return None
        assert dv.StatusCode.is_good(), dv.StatusCode
        return dv.Value.Value.Text

    async def states(self) -> tuple[str | None, str | None, str | None]:
        return (await self.current("Base"), await self.current("Machine"), await self.current("Execute"))

    async def wait(self, expected: tuple[str | None, str | None, str | None]) -> None:
        deadline = time.monotonic() + TIMEOUT
        while (got := await self.states()) != expected:
            assert time.monotonic() < deadline, f"waited for {expected}, unit is {got}"
            await asyncio.sleep(0.02)
        await self.check_ids(expected)

    async def check_ids(self, expected: tuple[str | None, ...]) -> None:
        for machine, state in zip(MACHINES, expected, strict=True):
            base = MACHINES[machine]
            if state is None:
                for sub in ("CurrentState", "CurrentState.Id", "LastTransition", "LastTransition.Id"):
                    dv = await self.node(f"{base}.{sub}").read_data_value(raise_on_bad_status=False)
                    assert dv.StatusCode.value == ua.StatusCodes.BadStateNotActive, (machine, sub)
                continue
            uri, ident = self.tables[machine].states[state].node
            assert uri == PACKML
            assert await self.node(f"{base}.CurrentState.Id").read_value() == ua.NodeId(ident, self.pml)
            assert await self.node(f"{base}.CurrentState.Number").read_value() == NUMBERS[state]

    async def count(self, which: str = "ProdProcessedCount") -> tuple[int, int]:
        (c,) = await self.value(f"Admin.{which}")
        return c.Count, c.AccCount


class Events:
    """TransitionEvents received through the Server object, as (machine, transition, from, to)."""

    def __init__(self, unit: Unit, app: UacellServer) -> None:
        self.by_node = {ua.NodeId(p, unit.ns): m for m, p in MACHINES.items()}
        self.got: list[tuple[str, str, str, str]] = []
        self.app = app

    def event_notification(self, event) -> None:
        if event.SourceNode not in self.by_node and event.SourceNode != ua.NodeId(ua.ObjectIds.Server):
            return  # another companion's machine (the unit's Machinery state, docs/machinery.md)
        self.got.append(
            (
                self.by_node.get(event.SourceNode, str(event.SourceNode)),
                event.Transition.Text,
                event.FromState.Text,
                event.ToState.Text,
            )
        )

    async def expect(self, *expected: tuple[str, str, str, str]) -> None:
        deadline = time.monotonic() + TIMEOUT
        while len(self.got) < len(expected):
            assert time.monotonic() < deadline, f"events {self.got}, expected {expected}"
            await asyncio.sleep(0.02)
        # Nothing more may follow: whatever the server produced before the marker has arrived with it.
        marker = f"marker {uuid.uuid4().hex}"
        await fire_marker(self.app, ua.NodeId(ua.ObjectIds.Server), marker)
        await wait_until(lambda: any(g[1] == marker for g in self.got), timeout=TIMEOUT)
        self.got[:] = [g for g in self.got if g[1] != marker]
        assert self.got == list(expected)
        self.got.clear()


class Changes:
    """Data changes of Status/StateRequested and Status/StateChangeInProcess, in order."""

    def __init__(self) -> None:
        self.got: dict[str, list[object]] = {}
        self.names: dict[object, str] = {}

    def datachange_notification(self, node, val, data) -> None:
        self.got.setdefault(self.names[node], []).append(val)

    def distinct(self, name: str) -> list[object]:
        out: list[object] = []
        for v in self.got.get(name, []):
            if not out or out[-1] != v:
                out.append(v)
        return out


JOB_STATES = {
    "Starting",
    "Execute",
    "Completing",
    "Holding",
    "Held",
    "Unholding",
    "Suspending",
    "Suspended",
    "Unsuspending",
}
SM_METHODS = [
    (BASE, "Abort", "Base"),
    (BASE, "Clear", "Base"),
    (MACH, "Stop", "Machine"),
    (MACH, "Reset", "Machine"),
    (EXEC, "Reset", "Execute"),
    (EXEC, "Start", "Execute"),
    (EXEC, "Hold", "Execute"),
    (EXEC, "Unhold", "Execute"),
    (EXEC, "Suspend", "Execute"),
    (EXEC, "Unsuspend", "Execute"),
    (EXEC, "ToComplete", "Execute"),
]
UNIT_METHODS = ["SetUnitMode", "SetMachSpeed", "SetProduct", "SetParameter", "RemoteCommand", "SetInterlock"]


async def check_executable(u: Unit, state: str) -> None:
    """Decision 4, read over the client: each method's Executable attribute in ``state`` (mode Produce)
    against the OPC 30050 v1.01 command table (as typed in test_packml_model)."""
    from test_packml_model import ALLOWED_PRODUCE

    machine_names = {"Base": "BaseStateMachine", "Machine": "MachineState", "Execute": "ExecuteState"}
    expected = {f"{obj}.{m}": (machine_names[k], m) in ALLOWED_PRODUCE[state] for obj, m, k in SM_METHODS}
    expected |= {
        f"{F}.{m}": {
            "SetUnitMode": state in {"Stopped", "Idle", "Aborted"},
            "SetProduct": state not in JOB_STATES,
            "SetParameter": state not in JOB_STATES,
        }.get(m, True)
        for m in UNIT_METHODS
    }
    deadline = time.monotonic() + TIMEOUT
    while True:  # completions refresh Executable through the publisher, just after CurrentState
        got = {path: (await u.node(path).read_attribute(ua.AttributeIds.Executable)).Value.Value for path in expected}
        if got == expected:
            return
        assert time.monotonic() < deadline, (state, {p: v for p, v in got.items() if v != expected[p]})
        await asyncio.sleep(0.02)


async def make_unit(client: Client) -> Unit:
    return Unit(client, await client.get_namespace_index(CELL), await client.get_namespace_index(PACKML))


def descriptors(*items: tuple[int, str, float]) -> ua.Variant:
    values = [
        ua.PackMLDescriptorDataType(
            ID=i,
            Name=n,
            Unit=ua.EUInformation(
                NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact",
                UnitId=4408652,
                DisplayName=ua.LocalizedText("°C"),
            ),
            Value=v,
        )
        for i, n, v in items
    ]
    return ua.Variant(values, ua.VariantType.ExtensionObject, is_array=True)


def f32(x: float) -> ua.Variant:
    return ua.Variant(x, ua.VariantType.Float)


def i32(x: int) -> ua.Variant:
    return ua.Variant(x, ua.VariantType.Int32)


async def test_full_walk_with_states_events_speed_and_production(app, client):
    u = await make_unit(client)
    ev = Events(u, app)
    sub = await client.create_subscription(20, ev)
    await sub.subscribe_events(client.get_node(ua.ObjectIds.Server), client.get_node(ua.ObjectIds.TransitionEventType))
    changes = Changes()
    status_sub = await client.create_subscription(20, changes)
    for name in ("StateRequested", "StateChangeInProcess"):
        node = u.node(f"{F}.Status.{name}")
        changes.names[node] = name
        await status_sub.subscribe_data_change(node, queuesize=100, sampling_interval=0)
    # the initial values have arrived: later notifications are changes
    await wait_until(lambda: set(changes.got) == {"StateRequested", "StateChangeInProcess"})

    await u.wait(("Cleared", "Stopped", None))  # decision 23; Execute inactive while Stopped
    await check_executable(u, "Stopped")
    # Decision 29: each machine's AvailableStates/AvailableTransitions are the NodeIds of its own
    # states/transitions in the type.
    for machine, path in MACHINES.items():
        table = u.tables[machine]
        states = await u.node(f"{path}.AvailableStates").read_value()
        assert sorted(states, key=str) == sorted((ua.NodeId(s.node[1], u.pml) for s in table.states.values()), key=str)
        transitions = await u.node(f"{path}.AvailableTransitions").read_value()
        assert sorted(transitions, key=str) == sorted(
            (ua.NodeId(t.node[1], u.pml) for t in table.transitions.values()), key=str
        )
        assert (len(states), len(transitions)) == {"Base": (3, 3), "Machine": (4, 4), "Execute": (12, 19)}[machine]
    assert await u.value("Status.CurMachSpeed") == 0.0
    await u.ok(MACH, "Reset")
    await u.wait(("Cleared", "Running", "Idle"))
    await ev.expect(
        ("Machine", "StoppedToRunning", "Stopped", "Running"), ("Execute", "ResettingToIdle", "Resetting", "Idle")
    )

    await u.ok(F, "SetMachSpeed", f32(600.0))  # 10 packages/s, so counts grow quickly
    assert await u.value("Status.MachSpeed") == 600.0
    count0 = await u.count()
    await check_executable(u, "Idle")
    await u.ok(EXEC, "Start", descriptors((1, "Temperature", 180.5), (2, "Fill", 0.25)))
    await u.wait(("Cleared", "Running", "Execute"))
    await ev.expect(
        ("Execute", "IdleToStarting", "Idle", "Starting"), ("Execute", "StartingToExecute", "Starting", "Execute")
    )
    await check_executable(u, "Execute")
    params = await u.value("Status.StartParameters")
    assert [(p.ID, p.Name, p.Value, p.Unit.UnitId, p.Unit.DisplayName.Text) for p in params] == [
        (1, "Temperature", 180.5, 4408652, "°C"),
        (2, "Fill", 0.25, 4408652, "°C"),
    ]
    assert await u.value("Status.Parameter") == []  # Start does not touch Status/Parameter
    assert await u.value("Status.CurMachSpeed") == 600.0
    deadline = time.monotonic() + TIMEOUT
    while (await u.count())[0] < count0[0] + 3:
        assert time.monotonic() < deadline, "ProdProcessedCount does not grow in Execute"
        await asyncio.sleep(0.05)
    count1 = await u.count()
    assert count1[1] - count0[1] == count1[0] - count0[0]  # AccCount grows with Count

    await u.ok(EXEC, "Hold")
    await u.wait(("Cleared", "Running", "Held"))
    await ev.expect(
        ("Execute", "ExecuteToHolding", "Execute", "Holding"), ("Execute", "HoldingToHeld", "Holding", "Held")
    )
    await check_executable(u, "Held")
    assert await u.value("Status.CurMachSpeed") == 0.0
    await app.settle()
    held = await u.count()
    # No production outside Execute: let the unit's own tick poll the equipment over 0.3 s of its clock
    # (3 packages at 600/min), then settle so that anything produced would be published.
    unit = app.registry(UNITS)[F].unit
    polled: list[float] = []
    poll = unit.equipment.poll

    def spy(now: float) -> None:
        polled.append(now)
        poll(now)

    unit.equipment.poll = spy
    try:
        held_at = unit.now()
        await wait_until(lambda: bool(polled) and polled[-1] >= held_at + 0.3, timeout=TIMEOUT)
    finally:
        del unit.equipment.poll
    await app.settle()
    assert await u.count() == held

    await u.ok(EXEC, "Unhold")
    await u.wait(("Cleared", "Running", "Execute"))
    await ev.expect(
        ("Execute", "HeldToUnholding", "Held", "Unholding"), ("Execute", "UnholdingToExecute", "Unholding", "Execute")
    )
    await u.ok(EXEC, "Suspend")
    await u.wait(("Cleared", "Running", "Suspended"))
    await ev.expect(
        ("Execute", "ExecuteToSuspending", "Execute", "Suspending"),
        ("Execute", "SuspendingToSuspended", "Suspending", "Suspended"),
    )
    await check_executable(u, "Suspended")
    await u.ok(EXEC, "Unsuspend")
    await u.wait(("Cleared", "Running", "Execute"))
    await ev.expect(
        ("Execute", "SuspendedToUnsuspending", "Suspended", "Unsuspending"),
        ("Execute", "UnsuspendingToExecute", "Unsuspending", "Execute"),
    )
    await u.ok(EXEC, "ToComplete")
    await u.wait(("Cleared", "Running", "Complete"))
    await ev.expect(
        ("Execute", "ExecuteToCompleting", "Execute", "Completing"),
        ("Execute", "CompletingToComplete", "Completing", "Complete"),
    )
    assert await u.value("Status.CurMachSpeed") == 0.0
    await u.ok(EXEC, "Reset")
    await u.wait(("Cleared", "Running", "Idle"))
    await ev.expect(
        ("Execute", "CompleteToResetting", "Complete", "Resetting"), ("Execute", "ResettingToIdle", "Resetting", "Idle")
    )

    await u.ok(MACH, "Stop")
    await u.wait(("Cleared", "Stopped", None))
    await ev.expect(
        ("Machine", "RunningToStopping", "Running", "Stopping"), ("Machine", "StoppingToStopped", "Stopping", "Stopped")
    )
    res = await u.call(EXEC, "Hold")  # Execute inactive while Stopped
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState

    await u.ok(BASE, "Abort")
    await u.wait(("Aborted", None, None))
    await ev.expect(
        ("Base", "ClearedToAborting", "Cleared", "Aborting"), ("Base", "AbortingToAborted", "Aborting", "Aborted")
    )
    await check_executable(u, "Aborted")
    stop_reason = await u.value("Admin.StopReason")
    assert (stop_reason.ID, stop_reason.Message) == (3, "Stop commanded")  # first out since last Execute
    for obj, method in ((MACH, "Reset"), (MACH, "Stop"), (EXEC, "Start")):
        args = [descriptors()] if method == "Start" else []
        res = await u.call(obj, method, *args)
        assert res.StatusCode.value == ua.StatusCodes.BadInvalidState, method
    await u.ok(BASE, "Clear")
    await u.wait(("Cleared", "Stopped", None))
    await ev.expect(
        ("Base", "AbortedToCleared", "Aborted", "Cleared"), ("Machine", "ClearingToStopped", "Clearing", "Stopped")
    )
    assert [p.ID for p in await u.value("Status.StartParameters")] == [1, 2]  # kept until the next Start
    await check_executable(u, "Stopped")
    # Decision 29: while an acting state runs, StateChangeInProcess is true and StateRequested names the
    # state it leads to (Resetting -> Idle 4, Starting -> Execute 6, Holding -> Held 11, ...).
    deadline = time.monotonic() + TIMEOUT
    while changes.distinct("StateRequested")[-1:] != [2] or changes.distinct("StateChangeInProcess")[-1:] != [False]:
        assert time.monotonic() < deadline, changes.got
        await asyncio.sleep(0.02)
    assert changes.distinct("StateRequested") == [2, 4, 6, 11, 6, 5, 6, 17, 4, 2, 9, 2]
    # 11 acting states: Resetting, Starting, Holding, Unholding, Suspending, Unsuspending, Completing,
    # Resetting, Stopping, Aborting, Clearing
    assert changes.distinct("StateChangeInProcess") == [False, True] * 11 + [False]
    await status_sub.delete()
    await sub.delete()


async def test_start_errors_modes_speed_and_fault(app, client):
    u = await make_unit(client)
    start = u.node(f"{EXEC}.Start")

    async def executable() -> bool:
        return (await start.read_attribute(ua.AttributeIds.Executable)).Value.Value

    res = await u.call(EXEC, "Start", descriptors((1, "a", 1.0)))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState  # Stopped
    assert await executable() is False
    await u.ok(MACH, "Reset")
    await u.wait(("Cleared", "Running", "Idle"))
    assert await executable() is True
    await u.ok(EXEC, "Start", descriptors((7, "seed", 7.0)))
    await u.wait(("Cleared", "Running", "Execute"))
    res = await u.call(EXEC, "Start", descriptors((1, "a", 1.0)))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState  # Execute
    await u.ok(EXEC, "ToComplete")
    await u.wait(("Cleared", "Running", "Complete"))
    await u.ok(EXEC, "Reset")
    await u.wait(("Cleared", "Running", "Idle"))

    eu = ua.EUInformation(NamespaceUri="u", UnitId=1, DisplayName=ua.LocalizedText("m"))
    cases = [
        ([], ua.StatusCodes.BadArgumentsMissing, []),
        ([descriptors((1, "a", 1.0)), descriptors()], ua.StatusCodes.BadTooManyArguments, []),
        (
            [ua.Variant([eu], ua.VariantType.ExtensionObject, is_array=True)],
            ua.StatusCodes.BadTypeMismatch,
            [ua.StatusCodes.BadTypeMismatch],
        ),
        (
            [ua.Variant([1, 2], ua.VariantType.Int32, is_array=True)],
            ua.StatusCodes.BadTypeMismatch,
            [ua.StatusCodes.BadTypeMismatch],
        ),
        (
            [ua.Variant(descriptors((1, "a", 1.0)).Value[0], ua.VariantType.ExtensionObject)],  # scalar
            ua.StatusCodes.BadTypeMismatch,
            [ua.StatusCodes.BadTypeMismatch],
        ),
        (
            [descriptors((1, "a", 1.0), (2, "b", 2.0), (1, "c", 3.0))],
            ua.StatusCodes.BadInvalidArgument,
            [ua.StatusCodes.BadInvalidArgument],
        ),
        ([descriptors((1, "a", math.nan))], ua.StatusCodes.BadInvalidArgument, [ua.StatusCodes.BadInvalidArgument]),
        ([descriptors((1, "a", math.inf))], ua.StatusCodes.BadInvalidArgument, [ua.StatusCodes.BadInvalidArgument]),
    ]
    for args, code, arg_results in cases:
        res = await u.call(EXEC, "Start", *args)
        assert res.StatusCode.value == code, (args, res.StatusCode)
        assert [r.value for r in res.InputArgumentResults] == arg_results, args
    # wrong object / unknown object
    res = await u.call(EXEC, "Start", descriptors(), obj_id=ua.NodeId(MACH, u.ns))
    assert res.StatusCode.value == ua.StatusCodes.BadMethodInvalid
    res = await u.call(EXEC, "Start", descriptors(), obj_id=ua.NodeId("Filler1.Nowhere", u.ns))
    assert res.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown
    # nothing changed
    assert await u.states() == ("Cleared", "Running", "Idle")
    assert [(p.ID, p.Value) for p in await u.value("Status.StartParameters")] == [(7, 7.0)]

    # SetParameter / SetProduct (decision 27; engineers): validated as Start, replace Status/Parameter, Product
    app.users.add("boss", "engineer", "a long admin password")
    admin = Client(app.endpoint, timeout=30)
    admin.set_user("boss")
    admin.set_password("a long admin password")
    await admin.connect()
    try:
        eng = Unit(admin, u.ns, u.pml)
        res = await eng.call(F, "SetParameter", descriptors((3, "a", 1.0), (3, "b", 2.0)))
        assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
        assert [r.value for r in res.InputArgumentResults] == [ua.StatusCodes.BadInvalidArgument]
        await eng.ok(F, "SetParameter", descriptors((3, "Speed", 2.5)))
        assert [(p.ID, p.Name, p.Value) for p in await u.value("Status.Parameter")] == [(3, "Speed", 2.5)]
        product = ua.PackMLProductDataType(
            ProductID=12, ProcessVariables=descriptors((1, "Fill", 0.5)).Value, Ingredients=[]
        )
        await eng.ok(F, "SetProduct", ua.Variant([product], ua.VariantType.ExtensionObject, is_array=True))
        (got,) = await u.value("Status.Product")
        assert (got.ProductID, [(p.ID, p.Value) for p in got.ProcessVariables]) == (12, [(1, 0.5)])
        assert [(p.ID, p.Value) for p in await u.value("Status.StartParameters")] == [(7, 7.0)]  # untouched
    finally:
        await admin.disconnect()

    # unit modes (decision 26)
    assert await u.value("Status.UnitModeCurrent") == 1
    supported = await u.value("Status.UnitSupportedModes")
    assert supported.NamespaceIndex == u.pml
    assert (await client.get_node(supported).read_browse_name()).Name == "ProductionMaintenanceModeEnum"
    res = await u.call(F, "SetUnitMode", i32(7))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    await u.ok(F, "SetUnitMode", i32(3))
    assert await u.value("Status.UnitModeCurrent") == 3
    assert await u.value("Status.UnitModeChangeInProcess") is False
    assert await executable() is False
    res = await u.call(EXEC, "Start", descriptors())
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    assert await u.states() == ("Cleared", "Running", "Idle")
    await u.ok(F, "SetUnitMode", i32(2))  # Maintenance: Start allowed, Suspend not
    assert await executable() is True
    await u.ok(EXEC, "Start", descriptors())
    assert await u.value("Status.StartParameters") == []  # an empty array is a valid Start
    await u.wait(("Cleared", "Running", "Execute"))
    suspend = u.node(f"{EXEC}.Suspend")
    assert (await suspend.read_attribute(ua.AttributeIds.Executable)).Value.Value is False
    res = await u.call(EXEC, "Suspend")
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    res = await u.call(F, "SetUnitMode", i32(1))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState  # not in Execute
    assert (await u.node(f"{F}.SetParameter").read_attribute(ua.AttributeIds.Executable)).Value.Value is False
    assert await u.value("Status.UnitModeCurrent") == 2

    # MachSpeed against its EURange (decision 27) and CurMachSpeed in Execute (decision 29)
    rng = await u.value("Status.MachSpeed.EURange")
    assert isinstance(rng, ua.Range) and (rng.Low, rng.High) == (0.0, 600.0)
    for bad in (600.5, -1.0, math.nan):
        res = await u.call(F, "SetMachSpeed", f32(bad))
        assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument, bad
        assert [r.value for r in res.InputArgumentResults] == [ua.StatusCodes.BadInvalidArgument]
    assert await u.value("Status.MachSpeed") == 60.0  # config default, unchanged
    await u.ok(F, "SetMachSpeed", f32(120.0))
    assert await u.value("Status.MachSpeed") == 120.0
    assert await u.value("Status.CurMachSpeed") == 120.0

    # InjectFault: engineers and admins only; aborts the unit with an alarm and the StopReason
    fault = (i32(42), ua.Variant("jam at infeed", ua.VariantType.String))
    res = await u.call(F, "InjectFault", *fault)
    assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied  # anonymous = operator
    assert await u.states() == ("Cleared", "Running", "Execute")
    admin = Client(app.endpoint, timeout=30)
    admin.set_user("boss")
    admin.set_password("a long admin password")
    await admin.connect()
    try:
        res = await Unit(admin, u.ns, u.pml).call(F, "SetParameter", descriptors((4, "late", 1.0)))
        assert res.StatusCode.value == ua.StatusCodes.BadInvalidState  # not while a job runs
        assert [p.ID for p in await u.value("Status.Parameter")] == [3]
        res = await Unit(admin, u.ns, u.pml).call(F, "InjectFault", *fault)
    finally:
        await admin.disconnect()
    assert res.StatusCode.is_good(), res.StatusCode
    await u.wait(("Aborted", None, None))
    (alarm,) = await u.value("Admin.Alarm")
    assert (alarm.ID, alarm.Message, alarm.Category, alarm.Trigger) == (42, "jam at infeed", 1, True)
    stop = await u.value("Admin.StopReason")
    assert (stop.ID, stop.Message) == (42, "jam at infeed")
    await u.ok(BASE, "Clear")
    await u.wait(("Cleared", "Stopped", None))
    assert await u.value("Admin.Alarm") == []
    assert [(a.ID, a.Trigger) for a in await u.value("Admin.AlarmHistory")] == [(42, False)]


async def _start_app(data_dir: Path) -> UacellServer:
    return await start_app(fast_config(data_dir))


async def test_admin_counters_survive_a_restart(tmp_path):
    data = tmp_path / "data"
    app = await _start_app(data)
    try:
        async with Client(app.endpoint, timeout=30, watchdog_intervall=30.0) as client:
            await client.load_data_type_definitions()
            u = await make_unit(client)
            await u.ok(MACH, "Reset")
            await u.wait(("Cleared", "Running", "Idle"))
            await u.ok(F, "SetMachSpeed", f32(600.0))
            await u.ok(EXEC, "Start", descriptors())
            deadline = time.monotonic() + TIMEOUT
            while (await u.count())[0] < 5:
                assert time.monotonic() < deadline
                await asyncio.sleep(0.05)
            await u.ok(MACH, "Stop")
            await u.wait(("Cleared", "Stopped", None))
            before = await u.count()
            consumed = await u.count("ProdConsumedCount")
            times = await u.value("Admin.StateCumulativeTime")
    finally:
        await app.stop()
    assert (data / "packml" / "Filler1.json").is_file()
    app = await _start_app(data)
    try:
        async with Client(app.endpoint, timeout=30) as client:
            u = await make_unit(client)
            assert await u.count() == before
            assert await u.count("ProdConsumedCount") == consumed
            assert before[0] >= 5
            after = await u.value("Admin.StateCumulativeTime")
            assert after[1][NUMBERS["Execute"]] >= times[1][NUMBERS["Execute"]]  # Produce row, Execute column
            await u.wait(("Cleared", "Stopped", None))  # state is not restored, Admin data is
    finally:
        await app.stop()
