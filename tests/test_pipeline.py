"""The request pipeline (uacell/ua/pipeline.py) on a bare asyncua server: its stages see every request,
Call and Read are answered as asyncua answers them (the same results and status codes, with the
pipeline and without), and a Call that waits runs apart while the connection answers other requests."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, Server, ua
from helpers import free_port
from uaraw import Fault, RawClient, anonymous_token

from uacell.ua.pipeline import Next, Pipeline, Request

S = ua.StatusCodes
NS = "urn:uacell:test:pipeline"


class Recording:
    """A stage that notes each request's type and whether its answer came back."""

    def __init__(self) -> None:
        self.seen: list[tuple[int, str]] = []
        self.hold_reads: asyncio.Event | None = None  # set: a Read waits for it in this stage

    async def __call__(self, request: Request, call_next: Next) -> Any:
        kind = request.typeid.Identifier
        self.seen.append((kind, "in"))
        try:
            if kind == ua.ObjectIds.ReadRequest_Encoding_DefaultBinary and self.hold_reads is not None:
                await self.hold_reads.wait()
            return await call_next(request)
        finally:
            self.seen.append((kind, "out"))


class Bench:
    """A bare asyncua server, with the pipeline or without, a value and three methods."""

    def __init__(self, server: Server, ns: int, stage: Recording | None) -> None:
        self.server, self.ns, self.stage = server, ns, stage
        self.release = asyncio.Event()
        self.endpoint = ""


pytestmark = pytest.mark.asyncio(loop_scope="module")


@pytest_asyncio.fixture(scope="module", loop_scope="module", params=["pipeline", "asyncua"])
async def bench(request: pytest.FixtureRequest) -> AsyncIterator[Bench]:
    server = Server()
    await server.init()
    port = free_port()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/")
    ns = await server.register_namespace(NS)
    stage = Recording() if request.param == "pipeline" else None
    b = Bench(server, ns, stage)
    b.endpoint = f"opc.tcp://127.0.0.1:{port}/"
    obj = await server.nodes.objects.add_object(ua.NodeId("Bench", ns), ua.QualifiedName("Bench", ns))
    await obj.add_variable(ua.NodeId("Value", ns), ua.QualifiedName("Value", ns), 42)

    def double(parent: Any, x: ua.Variant) -> list[ua.Variant]:
        return [ua.Variant(x.Value * 2, ua.VariantType.Int32)]

    async def held(parent: Any, x: ua.Variant) -> list[ua.Variant]:
        await b.release.wait()
        return [ua.Variant(x.Value + 1, ua.VariantType.Int32)]

    def refuse(parent: Any) -> ua.StatusCode:
        return ua.StatusCode(S.BadInvalidState)

    i32 = [ua.VariantType.Int32]
    await obj.add_method(ua.NodeId("Double", ns), ua.QualifiedName("Double", ns), double, i32, i32)
    await obj.add_method(ua.NodeId("Held", ns), ua.QualifiedName("Held", ns), held, i32, i32)
    await obj.add_method(ua.NodeId("Refuse", ns), ua.QualifiedName("Refuse", ns), refuse, [], [])
    if stage is not None:
        Pipeline([stage]).install(server.iserver)
    await server.start()
    try:
        yield b
    finally:
        b.release.set()
        await server.stop()


async def test_calls_and_reads_answer_alike_with_the_pipeline(bench: Bench) -> None:
    ns = bench.ns
    async with Client(bench.endpoint, timeout=10) as client:
        obj = client.get_node(ua.NodeId("Bench", ns))
        assert await obj.call_method(ua.NodeId("Double", ns), ua.Variant(21, ua.VariantType.Int32)) == 42
        with pytest.raises(ua.uaerrors.BadInvalidState):
            await obj.call_method(ua.NodeId("Refuse", ns))
        with pytest.raises(ua.uaerrors.BadNodeIdInvalid):  # asyncua's code for an unknown object
            await client.get_node(ua.NodeId("Missing", ns)).call_method(ua.NodeId("Double", ns), 1)
        assert await client.get_node(ua.NodeId("Value", ns)).read_value() == 42
        dv = (await client.uaclient.read_attributes([ua.NodeId("Missing", ns)], ua.AttributeIds.Value))[0]
        assert dv.StatusCode.value == S.BadNodeIdUnknown
    if bench.stage is not None:  # the stage saw each request in and out (the calls and reads among them)
        kinds = [k for k, way in bench.stage.seen if way == "in"]
        assert kinds.count(ua.ObjectIds.CallRequest_Encoding_DefaultBinary) == 3
        assert kinds.count(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary) >= 2
        assert bench.stage.seen.count((ua.ObjectIds.CallRequest_Encoding_DefaultBinary, "out")) == 3


async def test_a_waiting_call_does_not_hold_up_the_connection(bench: Bench) -> None:
    ns = bench.ns
    async with Client(bench.endpoint, timeout=10) as client:
        obj = client.get_node(ua.NodeId("Bench", ns))
        held = asyncio.create_task(obj.call_method(ua.NodeId("Held", ns), ua.Variant(1, ua.VariantType.Int32)))
        if bench.stage is None:  # asyncua alone answers one request of a connection after the other
            bench.release.set()
            assert await held == 2
            return
        # the same connection reads and calls while the held call waits
        assert await client.get_node(ua.NodeId("Value", ns)).read_value() == 42
        assert await obj.call_method(ua.NodeId("Double", ns), ua.Variant(5, ua.VariantType.Int32)) == 10
        assert not held.done()
        bench.release.set()
        assert await asyncio.wait_for(held, 10) == 2


async def test_a_session_not_activated_is_refused_alike(bench: Bench) -> None:
    port = int(bench.endpoint.rsplit(":", 1)[1].rstrip("/"))
    async with await RawClient.connect("127.0.0.1", port) as raw:
        await raw.hello()
        await raw.open_channel()
        with pytest.raises(Fault) as no_session:
            await raw.call(
                ua.NodeId("Bench", bench.ns), ua.NodeId("Double", bench.ns), [ua.Variant(1, ua.VariantType.Int32)]
            )
        assert no_session.value.code == S.BadUserAccessDenied  # asyncua's answer for a request without a session
        await raw.create_session()
        with pytest.raises(Fault) as not_activated:
            await raw.call(
                ua.NodeId("Bench", bench.ns), ua.NodeId("Double", bench.ns), [ua.Variant(1, ua.VariantType.Int32)]
            )
        assert not_activated.value.code == S.BadUserAccessDenied  # asyncua: the session has no user yet
        with pytest.raises(Fault) as not_activated:
            await raw.read_value(ua.NodeId("Value", bench.ns))
        assert not_activated.value.code == S.BadUserAccessDenied  # asyncua: the session has no user yet
        await raw.activate_session(anonymous_token())
        assert (await raw.read_value(ua.NodeId("Value", bench.ns))).Value.Value == 42
        result = await raw.call(
            ua.NodeId("Bench", bench.ns), ua.NodeId("Double", bench.ns), [ua.Variant(4, ua.VariantType.Int32)]
        )
        assert result.StatusCode.is_good() and result.OutputArguments[0].Value == 8


async def _until(condition: Any, timeout: float = 10.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not condition():
        assert asyncio.get_running_loop().time() < deadline, "condition not met in time"
        await asyncio.sleep(0.005)


async def test_a_request_that_waits_holds_back_the_next_of_its_connection(bench: Bench) -> None:
    """A message runs at once when its connection has nothing under way (no task switch), but one
    that waits still holds back the next of the same connection, as asyncua's task would: the second
    Read waits, queued, until the first is answered."""
    if bench.stage is None:
        pytest.skip("a waiting stage needs the pipeline")
    ns, stage = bench.ns, bench.stage
    read = ua.ObjectIds.ReadRequest_Encoding_DefaultBinary
    async with Client(bench.endpoint, timeout=10) as client:
        value = client.get_node(ua.NodeId("Value", ns))
        assert await value.read_value() == 42  # at once: nothing was under way
        stage.seen.clear()
        stage.hold_reads = release = asyncio.Event()
        try:
            first = asyncio.create_task(value.read_value())
            await _until(lambda: stage.seen == [(read, "in")])
            second = asyncio.create_task(value.read_value())
            connection = bench.server.bserver.clients[0]
            await _until(lambda: connection.messages.qsize() == 1)  # arrived, and waits its turn
            assert stage.seen == [(read, "in")]
        finally:
            stage.hold_reads = None
            release.set()
        assert await asyncio.wait_for(first, 10) == 42
        assert await asyncio.wait_for(second, 10) == 42
    assert stage.seen[:4] == [(read, "in"), (read, "out"), (read, "in"), (read, "out")]


async def test_messages_of_one_connection_start_in_the_order_they_came(monkeypatch: pytest.MonkeyPatch) -> None:
    """The connection's task and the messages run at once never overtake each other: A runs at once and
    waits; B arrives, is taken by the task, and waits for A; C arrives in the moment after A is done and
    before the task resumes B. C must still come after B (the task's claim on B holds it back)."""
    from uacell.ua.door import processing as pipeline  # asyncua's request path, wrapped by the door

    started: list[str] = []
    release = asyncio.Event()
    loop = asyncio.get_running_loop()

    class Connection:
        def __init__(self) -> None:
            self.messages: asyncio.Queue[Any] = asyncio.Queue(maxsize=10)
            self.peer_name = ("127.0.0.1", 1)

    def parse(protocol: Any, data: bytes) -> None:  # asyncua's data_received: one message a call
        protocol.messages.put_nowait((data.decode(), None))

    async def process(protocol: Any, header: str, buf: Any) -> bool:
        started.append(header)
        if header == "A":
            await release.wait()
            # runs after A's task is done and before the connection's task resumes B
            loop.call_soon(pipeline._received, protocol, b"C")
        return True

    monkeypatch.setattr(pipeline, "_ORIGINAL_DATA_RECEIVED", parse)
    monkeypatch.setattr(pipeline, "_ORIGINAL_PROCESS_ONE_MSG", process)
    connection = Connection()

    async def connection_task() -> None:  # asyncua's _process_received_message_loop
        while True:
            header, buf = await connection.messages.get()
            await pipeline._process_one_msg(connection, header, buf)

    task = asyncio.create_task(connection_task())
    try:
        pipeline._received(connection, b"A")
        assert started == ["A"]  # at once, and waiting
        pipeline._received(connection, b"B")
        await _until(lambda: connection.messages.empty())  # the task took B: it waits for A
        release.set()
        await _until(lambda: len(started) == 3)
        assert started == ["A", "B", "C"]
        pipeline._received(connection, b"D")
        assert started == ["A", "B", "C", "D"]  # idle again: at once
    finally:
        task.cancel()
