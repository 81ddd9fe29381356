"""Issue-12 findings 5 and 6: every method of the demo cell, with random and malformed arguments, from
every role, in whatever states the calls lead to. Never Bad_InternalError or Bad_UnexpectedError, never
an ERROR line or a traceback in the log, state machines consistent with their nodes, a server that
still answers. Bounded: a fixed (derandomized) set of a few thousand calls.

The server runs in an event loop of its own thread so that Hypothesis can drive it from a plain test.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import threading
from collections.abc import Coroutine, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import robot_binding, robot_cell
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_robotics_model import check_consistent

from uacell.core.roles import Role
from uacell.packml.binding import UNITS
from uacell.server import UacellServer

T = TypeVar("T")
EXAMPLES = 200
CALLS_PER_EXAMPLE = (5, 25)  # about 1,900 calls in all
INTERNAL = {ua.StatusCodes.BadInternalError, ua.StatusCodes.BadUnexpectedError}
PROGRAM_NAMES = ["pick_and_place", "palletize", "gripper", "nothing", "", "x" * 300]
ROBOT = "Robot1.Controllers.Controller1"
TC = f"{ROBOT}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
SO = f"{ROBOT}.SystemOperation.SystemOperationStateMachine"
PACKML = {"BaseStateMachine": "Filler1.BaseStateMachine"}


class Problems(logging.Handler):
    """Every ERROR-or-worse record and every record with a traceback."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.levelno >= logging.ERROR or record.exc_info:
            self.records.append(record)


@dataclasses.dataclass
class Target:
    object_id: ua.NodeId
    method_id: ua.NodeId
    name: str
    inputs: list[ua.Argument]


class Rig:
    def __init__(self, data_dir: Path) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="fuzz-server", daemon=True)
        self.thread.start()
        self.app: UacellServer = self.run(start_app(fast_config(data_dir)))
        self.clients: dict[Role, Client] = {}
        self.targets: list[Target] = []
        self.node_pool: list[ua.NodeId] = []
        self.answers: dict[str, int] = {}
        self.run(self._setup())

    def run(self, coro: Coroutine[Any, Any, T], timeout: float = 300.0) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    async def _setup(self) -> None:
        manager = self.app.server.iserver.user_manager
        for role in Role:
            manager.policy = dataclasses.replace(manager.policy, anonymous_role=role)
            client = Client(self.app.endpoint, timeout=30)
            await client.connect()
            self.clients[role] = client
        manager.policy = dataclasses.replace(manager.policy, anonymous_role=Role.OPERATOR)
        dispatcher = self.app.dispatcher
        aspace = self.app.server.iserver.aspace
        for bound in dispatcher.methods.values():
            self.targets.append(Target(bound.object_id, bound.method_id, bound.name, bound.inputs))
        # Standard methods uacell does not implement itself: ConditionRefresh(2) on ConditionType (as
        # OPC 10000-9 says) and on every condition, with the ids of the type's declarations.
        conditions = [ua.NodeId(ua.ObjectIds.ConditionType)]
        conditions += [c.node for c in robot_binding(self.app).conditions.nodes.values()]
        for name, ident in (
            ("ConditionRefresh", ua.ObjectIds.ConditionType_ConditionRefresh),
            ("ConditionRefresh2", ua.ObjectIds.ConditionType_ConditionRefresh2),
        ):
            method = ua.NodeId(ident)
            for obj in conditions:
                self.targets.append(Target(obj, method, name, dispatcher.arguments(method, "InputArguments")))
        files = robot_binding(self.app).programs.directory
        assert files is not None
        self.node_pool = [files.node_of(e.relpath) for e in robot_binding(self.app).store.entries()]
        self.node_pool += [ua.NodeId(0, 0), ua.NodeId("no.such.node", 2), ua.NodeId(ua.ObjectIds.Server)]
        assert all(t.method_id in aspace for t in self.targets)

    def close(self) -> None:
        async def stop() -> None:
            for client in self.clients.values():
                try:
                    await asyncio.wait_for(client.disconnect(), 10)
                except Exception:
                    pass
            await self.app.stop()

        try:
            self.run(stop())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(30)
            self.loop.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    r = Rig(tmp_path_factory.mktemp("fuzz") / "data")
    try:
        yield r
    finally:
        r.close()


@pytest.fixture(scope="module")
def problems() -> Iterator[Problems]:
    handler = Problems()
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield handler
    finally:
        root.removeHandler(handler)


# --- arguments ------------------------------------------------------------------------------------------
_INT_RANGES = {
    ua.VariantType.SByte: (-(2**7), 2**7 - 1),
    ua.VariantType.Byte: (0, 2**8 - 1),
    ua.VariantType.Int16: (-(2**15), 2**15 - 1),
    ua.VariantType.UInt16: (0, 2**16 - 1),
    ua.VariantType.Int32: (-(2**31), 2**31 - 1),
    ua.VariantType.UInt32: (0, 2**32 - 1),
    ua.VariantType.Int64: (-(2**63), 2**63 - 1),
    ua.VariantType.UInt64: (0, 2**64 - 1),
}


def _scalar(rig: Rig, vtype: ua.VariantType | None, datatype: ua.NodeId) -> st.SearchStrategy[Any]:
    if vtype in _INT_RANGES:
        low, high = _INT_RANGES[vtype]
        return st.one_of(st.integers(max(low, -2), min(high, 8)), st.integers(low, high))
    if vtype is ua.VariantType.Boolean:
        return st.booleans()
    if vtype in (ua.VariantType.Float, ua.VariantType.Double):
        return st.one_of(st.floats(-10, 200), st.floats(allow_nan=True, allow_infinity=True, width=32))
    if vtype is ua.VariantType.String:
        return st.one_of(st.sampled_from(PROGRAM_NAMES), st.text(max_size=20))
    if vtype is ua.VariantType.ByteString:
        programs = [b"program Fuzz\nwait 0\n", b"program Bad\nmove 1\n", b"\xff\xfe\x00"]
        return st.one_of(st.sampled_from(programs), st.binary(max_size=64))
    if vtype is ua.VariantType.NodeId:
        return st.sampled_from(rig.node_pool)
    if vtype is ua.VariantType.ExpandedNodeId:
        return st.sampled_from(rig.node_pool).map(lambda n: ua.ExpandedNodeId(n.Identifier, n.NamespaceIndex))
    if vtype is ua.VariantType.QualifiedName:
        return st.text(max_size=10).map(ua.QualifiedName)
    if vtype is ua.VariantType.LocalizedText:
        return st.text(max_size=10).map(ua.LocalizedText)
    if vtype is ua.VariantType.ExtensionObject:
        cls = ua.extension_objects_by_datatype.get(datatype)
        return st.just(cls()) if cls is not None else st.just(ua.ExtensionObject())
    return st.nothing()


def _good(rig: Rig, arg: ua.Argument) -> st.SearchStrategy[ua.Variant]:
    vtype = rig.app.dispatcher.types.builtin_of(arg.DataType)
    variant_type = vtype or ua.VariantType.Int32
    scalar = _scalar(rig, vtype, arg.DataType)
    if scalar.is_empty:
        return st.just(ua.Variant())  # a type the fuzzer has no values for: Null
    if arg.ValueRank >= 0:
        return st.lists(scalar, max_size=3).map(lambda v: ua.Variant(v, variant_type, is_array=True))
    return scalar.map(lambda v: ua.Variant(v, variant_type))


# ExtensionObjects the server knows the type of, with a body that does not decode or no body at all.
_KNOWN = ua.NodeId(ua.ObjectIds.Argument_Encoding_DefaultBinary)
BAD = st.sampled_from(
    [
        ua.Variant(),
        ua.Variant("not a number", ua.VariantType.String),
        ua.Variant(3.5, ua.VariantType.Double),
        ua.Variant([1, 2], ua.VariantType.Int32, is_array=True),
        ua.Variant(ua.ExtensionObject(TypeId=_KNOWN, Body=b"\x01\x02"), ua.VariantType.ExtensionObject),
        ua.Variant(ua.ExtensionObject(TypeId=_KNOWN, Body=None), ua.VariantType.ExtensionObject),
        ua.Variant(ua.ExtensionObject(TypeId=ua.NodeId(99999, 0), Body=b"junk"), ua.VariantType.ExtensionObject),
        ua.Variant(b"\xff\xfe invalid UTF-8", ua.VariantType.String),
    ]
)


@st.composite
def calls(draw: st.DrawFn, rig: Rig) -> tuple[Role, Target, list[ua.Variant]]:
    target = draw(st.sampled_from(rig.targets))
    role = draw(st.sampled_from(list(Role)))
    args = [draw(st.one_of(_good(rig, a), _good(rig, a), _good(rig, a), BAD)) for a in target.inputs]
    shape = draw(st.sampled_from(["as declared"] * 8 + ["one missing", "one extra"]))
    if shape == "one missing" and args:
        args.pop()
    elif shape == "one extra":
        args.append(draw(BAD))
    return role, target, args


async def _call(rig: Rig, role: Role, target: Target, args: list[ua.Variant]) -> int:
    request = ua.CallMethodRequest(ObjectId=target.object_id, MethodId=target.method_id, InputArguments=args)
    try:
        (result,) = await asyncio.wait_for(rig.clients[role].uaclient.call([request]), 30)
    except ua.UaStatusCodeError as exc:  # the whole request refused (Bad_DecodingError)
        return exc.code
    return result.StatusCode.value


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_no_client_input_causes_an_internal_error(rig: Rig, problems: Problems, data: st.DataObject) -> None:
    batch = data.draw(st.lists(calls(rig), min_size=CALLS_PER_EXAMPLE[0], max_size=CALLS_PER_EXAMPLE[1]))
    for role, target, args in batch:
        code = rig.run(_call(rig, role, target, args))
        name = ua.StatusCode(code).name
        rig.answers[name] = rig.answers.get(name, 0) + 1
        assert code not in INTERNAL, f"{target.name} by {role.label} with {args!r}: {name}"
        assert not problems.records, [r.getMessage() for r in problems.records]


def test_known_refusals_of_methods_uacell_does_not_implement(rig: Rig, problems: Problems) -> None:
    refresh = next(t for t in rig.targets if t.name == "ConditionRefresh")
    refresh2 = next(t for t in rig.targets if t.name == "ConditionRefresh2")
    admin = Role.ADMIN
    assert rig.run(_call(rig, admin, refresh, [])) == ua.StatusCodes.BadArgumentsMissing
    assert (
        rig.run(_call(rig, admin, refresh, [ua.Variant("1", ua.VariantType.String)])) == ua.StatusCodes.BadTypeMismatch
    )
    two = [ua.Variant(1, ua.VariantType.UInt32)] * 3
    assert rig.run(_call(rig, admin, refresh2, two)) == ua.StatusCodes.BadTooManyArguments
    unknown = [ua.Variant(123456, ua.VariantType.UInt32)]
    assert rig.run(_call(rig, admin, refresh, unknown)) == ua.StatusCodes.BadSubscriptionIdInvalid
    assert not problems.records


def test_malformed_extension_objects_answer_bad_decoding_error(rig: Rig, problems: Problems) -> None:
    set_parameter = next(t for t in rig.targets if t.name == "SetParameter")
    for body in (None, b"\x01\x02"):
        eo = ua.Variant(ua.ExtensionObject(TypeId=_KNOWN, Body=body), ua.VariantType.ExtensionObject)
        args = [eo] * len(set_parameter.inputs)
        assert rig.run(_call(rig, Role.ADMIN, set_parameter, args)) == ua.StatusCodes.BadDecodingError
    unknown = ua.Variant(ua.ExtensionObject(TypeId=ua.NodeId(99999, 0), Body=b"junk"), ua.VariantType.ExtensionObject)
    args = [unknown] * len(set_parameter.inputs)
    assert rig.run(_call(rig, Role.ADMIN, set_parameter, args)) == ua.StatusCodes.BadTypeMismatch
    assert not problems.records
    assert rig.run(_call(rig, Role.OBSERVER, set_parameter, [])) == ua.StatusCodes.BadArgumentsMissing


def test_after_the_fuzzing_the_server_is_consistent_and_answers(rig: Rig, problems: Problems) -> None:
    assert sum(rig.answers.values()) >= 1500, rig.answers
    assert rig.answers.get("Good", 0) > 0 and len(rig.answers) > 5  # calls got through and were refused

    async def check() -> None:
        await rig.app.settle()
        check_consistent(robot_cell(rig.app))
        client = rig.clients[Role.OBSERVER]
        ns = await client.get_namespace_index("urn:uacell:cell")
        task = robot_cell(rig.app).tasks["TaskControl1"]
        for path, model in ((TC, task.machine), (SO, robot_cell(rig.app).system.machine)):
            text = (await client.get_node(ua.NodeId(f"{path}.CurrentState", ns)).read_value()).Text
            assert text == model.current, path
        unit = rig.app.registry(UNITS).values()[0].unit
        for machine in unit.machines.values():
            if machine.active:
                node = ua.NodeId(f"Filler1.{_packml_path(machine.name)}.CurrentState", ns)
                assert (await client.get_node(node).read_value()).Text == machine.current
        assert await client.nodes.server_state.read_value() == ua.ServerState.Running

    rig.run(check())
    assert not problems.records, [r.getMessage() for r in problems.records]


def _packml_path(name: str) -> str:
    return {"BaseStateMachine": "BaseStateMachine", "MachineState": "BaseStateMachine.MachineState"}.get(
        name, "BaseStateMachine.MachineState.ExecuteState"
    )
