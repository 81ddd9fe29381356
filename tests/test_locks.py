"""DI LockingServices on Controller1 and TaskControl1 over real sessions (decision 20).

One server for the module; every test leaves no lock behind.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import lock_manager, raw_call, server_value, wait_until
from uaraw import anonymous_token, none_session

from uacell.server import UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

CTRL = "Robot1.Controllers.Controller1"
TASK = f"{CTRL}.TaskControls.TaskControl1"
TC_SM = f"{TASK}.TaskControlOperation.TaskControlStateMachine"
SO_SM = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
PASSWORD = "pw-locks"


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory):
    server = await start_app(fast_config(tmp_path_factory.mktemp("locks") / "data"))
    server.users.add("alice", "operator", PASSWORD)
    server.users.add("bob", "operator", PASSWORD)
    server.users.add("erin", "engineer", PASSWORD)
    try:
        yield server
    finally:
        await server.stop()


@pytest.fixture(autouse=True)
def no_locks_left(app):
    yield
    manager = lock_manager(app)
    manager.max_inactive = 60.0
    for element in manager.locked_elements():
        manager.break_lock(element, by="test cleanup")


class Session:
    """A client session with the calls these tests need."""

    def __init__(self, app: UacellServer, uri: str, user: str | None = None) -> None:
        self.app = app
        self.client = Client(app.endpoint, timeout=20)
        self.client.application_uri = uri
        if user:
            self.client.set_user(user)
            self.client.set_password(PASSWORD)

    async def __aenter__(self) -> Session:
        await self.client.connect()
        self.ns = await self.client.get_namespace_index("urn:uacell:cell")
        return self

    async def __aexit__(self, *exc) -> None:
        await self.client.disconnect()

    async def call(self, obj: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
        return await raw_call(self.client, ua.NodeId(obj, self.ns), ua.NodeId(f"{obj}.{method}", self.ns), *args)

    async def lock(self, element: str, method: str, *args: ua.Variant) -> int | ua.StatusCode:
        """A Lock method's Int32 status, or the call's bad StatusCode."""
        res = await self.call(f"{element}.Lock", method, *args)
        if not res.StatusCode.is_good():
            return res.StatusCode
        return res.OutputArguments[0].Value

    async def init_lock(self, element: str, context: str = "test") -> int | ua.StatusCode:
        return await self.lock(element, "InitLock", ua.Variant(context, ua.VariantType.String))

    async def load(self) -> int:
        res = await self.call(TC_SM, "LoadByName", ua.Variant("no-such-program", ua.VariantType.String))
        return res.StatusCode.value

    async def get_ready(self) -> int:
        return (await self.call(SO_SM, "GetReady")).StatusCode.value

    async def var(self, element: str, name: str):
        return await self.client.get_node(ua.NodeId(f"{element}.Lock.{name}", self.ns)).read_value()


RESOURCE = ua.StatusCodes.BadResourceUnavailable
DENIED = ua.StatusCodes.BadUserAccessDenied


def refused(result: int | ua.StatusCode) -> int:
    """The StatusCode value of a Lock call the server refused (``Session.lock`` returns it, not a status)."""
    assert isinstance(result, ua.StatusCode), result
    return result.value


async def wait_unlocked(session: Session, element: str, within: float) -> float:
    """Seconds until ``element``'s Locked reads false (fails after ``within``)."""
    start = time.monotonic()
    while time.monotonic() - start < within:
        if await session.var(element, "Locked") is False:
            return time.monotonic() - start
        await asyncio.sleep(0.2)
    raise AssertionError(f"{element} still locked after {within} s")


async def test_two_sessions_contend_for_the_task_control(app):
    async with Session(app, "urn:test:a", "alice") as a, Session(app, "urn:test:b", "bob") as b:
        assert await a.init_lock(TASK, "recipe 7") == 0
        assert await b.load() == RESOURCE
        assert await a.load() not in (RESOURCE, DENIED)  # the owner may operate
        assert await b.init_lock(TASK) == -1  # E_AlreadyLocked
        assert await b.init_lock(CTRL) == -1  # a lock below the controller blocks it too
        assert await a.var(TASK, "Locked") is True
        assert await b.var(TASK, "LockingClient") == "urn:test:a"
        assert await b.var(TASK, "LockingUser") == "alice"
        assert 0 < await b.var(TASK, "RemainingLockTime") <= 60000
        assert await b.var(CTRL, "Locked") is False
        # only the owner renews or exits
        assert refused(await b.lock(TASK, "RenewLock")) == DENIED
        assert refused(await b.lock(TASK, "ExitLock")) == DENIED
        assert await a.lock(TASK, "RenewLock") == 0
        assert await a.lock(TASK, "ExitLock") == 0
        assert await a.lock(TASK, "ExitLock") == -1  # E_NotLocked
        assert await b.load() != RESOURCE
        assert await b.var(TASK, "Locked") is False
        assert await b.var(TASK, "LockingUser") == ""


async def test_controller_lock_covers_task_control_and_system_operation(app):
    async with Session(app, "urn:test:a", "alice") as a, Session(app, "urn:test:b") as b:
        assert await a.init_lock(CTRL) == 0
        assert await b.load() == RESOURCE
        assert await b.get_ready() == RESOURCE
        assert await a.get_ready() not in (RESOURCE, DENIED)
        assert await a.load() not in (RESOURCE, DENIED)
        assert await b.init_lock(TASK) == -1
        assert await a.init_lock(TASK) == 0  # the owner may narrow its own lock
        assert await a.lock(CTRL, "ExitLock") == 0
        assert await b.get_ready() != RESOURCE  # SystemOperation is free again
        assert await b.load() == RESOURCE  # TaskControl1 still locked by a


LOCKED = ua.StatusCodes.BadLocked
MODE = f"{TASK}.ParameterSet.ExecutionMode"


async def test_lock_covers_writes_from_other_sessions(app):
    """A hand-built anonymous session (operator on loopback) writes ExecutionMode past alice's locks."""
    raw, _ = await none_session("127.0.0.1", app.config.server.port)
    async with raw, Session(app, "urn:test:a", "alice") as a:
        await raw.activate_session(anonymous_token())
        mode = ua.NodeId(MODE, a.ns)
        node = a.client.get_node(mode)
        step, continuous = ua.Variant(2, ua.VariantType.Int32), ua.Variant(1, ua.VariantType.Int32)
        assert (await raw.write_value(mode, step)).value == ua.StatusCodes.Good  # operators may write it
        for element in (TASK, CTRL):  # the TaskControl's own lock, and its Controller's
            assert await a.init_lock(element) == 0
            assert (await raw.write_value(mode, continuous)).value == LOCKED
            assert await node.read_value() == 2  # unchanged
            await node.write_value(continuous)  # the owner writes
            assert await node.read_value() == 1
            await node.write_value(step)
            assert await a.lock(element, "ExitLock") == 0
        assert (await raw.write_value(mode, continuous)).value == ua.StatusCodes.Good  # free again
        assert await node.read_value() == 1
        await node.write_value(ua.Variant(0, ua.VariantType.Int32))


async def test_task_control_lock_leaves_system_operation_free(app):
    async with Session(app, "urn:test:a") as a, Session(app, "urn:test:b") as b:
        assert await a.init_lock(TASK) == 0
        assert await b.get_ready() != RESOURCE


async def test_break_lock_needs_engineer(app):
    async with (
        Session(app, "urn:test:a", "alice") as a,
        Session(app, "urn:test:b", "bob") as b,
        Session(app, "urn:test:e", "erin") as e,
    ):
        assert await a.init_lock(TASK) == 0
        assert refused(await b.lock(TASK, "BreakLock")) == DENIED
        assert await a.var(TASK, "Locked") is True
        assert await e.lock(TASK, "BreakLock") == 0
        assert await a.var(TASK, "Locked") is False
        assert await b.load() != RESOURCE
        assert await e.lock(TASK, "BreakLock") == -1


async def test_lock_ends_when_its_session_closes(app):
    async with Session(app, "urn:test:b") as b:
        async with Session(app, "urn:test:a") as a:
            assert await a.init_lock(TASK) == 0
            assert await b.load() == RESOURCE
        assert await wait_unlocked(b, TASK, 3.0) < 3.0
        assert await b.load() != RESOURCE


async def test_lock_expires_after_max_inactive_lock_time(app):
    lock_manager(app).max_inactive = 1.0
    async with Session(app, "urn:test:a") as a, Session(app, "urn:test:b") as b:
        assert await a.init_lock(TASK) == 0
        first = await b.var(TASK, "RemainingLockTime")
        remaining = ua.NodeId(f"{TASK}.Lock.RemainingLockTime", b.ns)
        # kept current while locked (the server's expiry tick updates it)
        await wait_until(lambda: server_value(app, remaining) < first, timeout=3.0)
        assert await b.var(TASK, "RemainingLockTime") < first
        assert await wait_unlocked(b, TASK, 3.0) < 3.0
        assert await b.load() != RESOURCE
        assert await a.lock(TASK, "RenewLock") == -1


_HOLDER = """
import asyncio, sys
from asyncua import Client, ua

async def main(endpoint, subscribe):
    client = Client(endpoint, timeout=20)
    client.application_uri = "urn:test:doomed"
    client.session_timeout = 5000  # the server's minimum
    await client.connect()
    ns = await client.get_namespace_index("urn:uacell:cell")
    if subscribe:
        # A session with a subscription outlives its connection: only the session timeout ends it.
        sub = await client.create_subscription(500, None)
        await sub.subscribe_data_change(client.get_node(ua.NodeId("{task}.Lock.Locked", ns)))
    lock = ua.NodeId("{task}.Lock", ns)
    status = await client.get_node(lock).call_method(ua.NodeId("{task}.Lock.InitLock", ns),
                                                     ua.Variant("doomed", ua.VariantType.String))
    print("locked", status, flush=True)
    await asyncio.sleep(600)

asyncio.run(main(sys.argv[1], sys.argv[2] == "1"))
""".replace("{task}", TASK)


@pytest.mark.parametrize("subscribed", [False, True], ids=["plain", "with-subscription"])
async def test_lock_freed_when_the_holding_process_is_killed(app, subscribed):
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        _HOLDER,
        app.endpoint,
        "1" if subscribed else "0",
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env=os.environ.copy(),
    )
    assert proc.stdout is not None
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), 60)
        assert line.decode().strip() == "locked 0", line
        async with Session(app, "urn:test:b") as b:
            assert await b.var(TASK, "LockingClient") == "urn:test:doomed"
            assert await b.load() == RESOURCE
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
            # Without a subscription the session ends with the connection; with one, after its
            # 5 s timeout (checked every second or so).
            took = await wait_unlocked(b, TASK, 15.0)
            assert took < (2.0 if not subscribed else 12.0)
            assert await b.load() != RESOURCE
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_max_inactive_lock_time_published(app):
    async with Session(app, "urn:test:a") as a:
        di = await a.client.get_namespace_index("http://opcfoundation.org/UA/DI/")
        value = await a.client.get_node(ua.NodeId(6387, di)).read_value()
        assert value == lock_manager(app).max_inactive_ms == 60000.0
