"""Issue-12 finding 4: login throttling keyed by user name (at one address and across addresses);
anonymous clients and other users are never delayed; password checks run off the event loop, a few
at a time server-wide."""

from __future__ import annotations

import asyncio
import itertools
import threading
import time
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import wait_until
from test_security import ClientCert, secure_client

from uacell import security
from uacell.pki import PkiPaths, TrustList
from uacell.roles import Role
from uacell.server import UacellServer
from uacell.users import LoginThrottle

pytestmark = pytest.mark.asyncio(loop_scope="module")

PASSWORD = "correct horse"


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


# --- pure ---------------------------------------------------------------------------------------------
async def test_failures_count_per_user_at_an_address_and_leave_others_alone() -> None:
    clock = Clock()
    t = LoginThrottle(base=1.0, cap=8.0, free=2, free_per_user=100, clock=clock)
    delays = [t.failed("alice", "10.0.0.9") for _ in range(7)]
    assert delays == [0.0, 0.0, 1.0, 2.0, 4.0, 8.0, 8.0]
    assert t.wait_time("alice", "10.0.0.9") == 8.0
    assert t.wait_time("bob", "10.0.0.9") == 0.0  # another user behind the same NAT
    assert t.wait_time("alice", "10.0.0.10") == 0.0  # alice elsewhere: only 7 of 100 failures so far
    clock.now += 5
    assert t.wait_time("alice", "10.0.0.9") == 3.0
    t.succeeded("alice", "10.0.0.9")
    assert t.wait_time("alice", "10.0.0.9") == 0.0
    assert t.failed("alice", "10.0.0.9") == 0.0  # counting starts afresh


async def test_changing_the_source_address_does_not_escape_the_user_count() -> None:
    clock = Clock()
    t = LoginThrottle(base=1.0, cap=30.0, free=2, free_per_user=10, clock=clock)
    delays = [t.failed("alice", f"127.0.0.{10 + i}") for i in range(20)]
    assert delays[:10] == [0.0] * 10  # one failure per address: only the user-wide count grows
    assert delays[10:14] == [1.0, 2.0, 4.0, 8.0]
    assert t.wait_time("alice", "127.0.0.99") == 30.0  # a fresh address waits as well
    assert t.wait_time("bob", "127.0.0.10") == 0.0


async def test_idle_entries_are_forgotten_and_their_number_is_bounded() -> None:
    clock = Clock()
    t = LoginThrottle(base=1.0, cap=30.0, free=0, free_per_user=0, forget_after=60.0, max_entries=100, clock=clock)
    t.failed("a", "x")
    clock.now += 61
    assert t.wait_time("a", "x") == 0.0
    for i in range(1000):  # a spray of user names
        clock.now += 0.001
        t.failed(f"user{i}", "x")
    assert len(t._failures) <= 100


# --- over TCP -----------------------------------------------------------------------------------------
@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def env(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[tuple[UacellServer, ClientCert]]:
    base = tmp_path_factory.mktemp("throttle")
    config = fast_config(base / "data")
    config.limits.login_base_delay, config.limits.login_max_delay = 2.0, 2.0
    config.limits.login_free_failures, config.limits.login_free_failures_per_user = 1, 3
    config.limits.password_checks = 2
    app = await start_app(config)
    cert = ClientCert(base / "client")
    TrustList(PkiPaths.in_data_dir(app.data_dir)).trust(cert.der)
    for i in range(6):
        app.users.add(f"user{i}", Role.OPERATOR, PASSWORD)
    try:
        yield app, cert
    finally:
        await app.stop()


@pytest.fixture(autouse=True)
def fresh_throttle(request: pytest.FixtureRequest) -> None:
    if "env" in request.fixturenames:
        app, _ = request.getfixturevalue("env")
        app.security.throttle = LoginThrottle(base=2.0, cap=2.0, free=1, free_per_user=3)


async def _login(app: UacellServer, cert: ClientCert, user: str, password: str) -> tuple[float, bool]:
    start = time.monotonic()
    client = await secure_client(app, cert, user=user, password=password, connect=False)
    try:
        await client.connect()
    except ua.UaStatusCodeError as exc:
        assert exc.code == ua.StatusCodes.BadUserAccessDenied
        return time.monotonic() - start, False
    await client.disconnect()
    return time.monotonic() - start, True


async def _anonymous(app: UacellServer) -> float:
    start = time.monotonic()
    async with Client(app.endpoint, timeout=20) as client:
        await client.nodes.server_state.read_value()
    return time.monotonic() - start


async def test_a_throttled_user_delays_neither_anonymous_clients_nor_other_users(env) -> None:  # type: ignore[no-untyped-def]
    app, cert = env
    await _login(app, cert, "user0", "wrong")
    await _login(app, cert, "user0", "wrong")  # from now on user0 waits 2 s at 127.0.0.1
    assert app.security.throttle.wait_time("user0", "127.0.0.1") > 1.0
    delayed = asyncio.create_task(_login(app, cert, "user0", PASSWORD))
    # user0's attempt holds its user's login lock while it waits out the delay.
    await wait_until(lambda: (lock := app.security._user_locks.get("user0")) is not None and lock.locked())
    anonymous = await _anonymous(app)
    other, ok = await _login(app, cert, "user1", PASSWORD)
    waited, user0_ok = await delayed
    assert ok and user0_ok
    assert waited >= 1.5
    assert anonymous < 1.5 and other < waited


async def test_rotating_source_addresses_still_delays_the_user(env, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    app, cert = env
    addresses = (f"127.0.0.{i}" for i in itertools.count(10))
    monkeypatch.setattr(security, "_address", lambda processor: next(addresses))
    for _ in range(3):  # one failure per address, within the free count of each address
        await _login(app, cert, "user2", "wrong")
    assert app.security.throttle.wait_time("user2", "127.0.0.200") == 0.0
    await _login(app, cert, "user2", "wrong")  # the user-wide count (3 free) is used up now
    assert app.security.throttle.wait_time("user2", "127.0.0.200") > 1.5  # an address never used before
    fifth, _ = await _login(app, cert, "user2", "wrong")
    assert fifth >= 1.8  # waited out the 2 s delay from a new address
    assert app.security.throttle.wait_time("user3", "127.0.0.200") == 0.0


async def test_password_checks_run_off_the_loop_at_most_a_few_at_once(env, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    app, cert = env
    active, peak = 0, 0
    threads: set[str] = set()
    guard = threading.Lock()
    original = app.users.verify

    def slow_verify(name: str, password: str) -> Role | None:
        nonlocal active, peak
        with guard:
            active += 1
            peak = max(peak, active)
            threads.add(threading.current_thread().name)
        try:
            time.sleep(0.3)
            return original(name, password)
        finally:
            with guard:
                active -= 1

    monkeypatch.setattr(app.users, "verify", slow_verify)
    logins = [asyncio.create_task(_login(app, cert, f"user{i}", PASSWORD)) for i in range(6)]
    results = await asyncio.gather(*logins)
    assert all(ok for _, ok in results)
    assert peak == 2
    assert threading.main_thread().name not in threads  # the event loop never hashed a password
