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
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from conftest import fast_config, start_app
from helpers import wait_until
from test_security import ClientCert, secure_client

from uacell.core.roles import Role
from uacell.security import policy as security
from uacell.security.pki import PkiPaths, TrustList
from uacell.security.users import LoginThrottle
from uacell.server import UacellServer

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


async def test_a_throttled_user_delays_neither_anonymous_clients_nor_other_users(env) -> None:
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


async def test_rotating_source_addresses_still_delays_the_user(env, monkeypatch: pytest.MonkeyPatch) -> None:
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


async def test_password_checks_run_off_the_loop_at_most_a_few_at_once(env, monkeypatch: pytest.MonkeyPatch) -> None:
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


async def test_attempts_of_one_name_share_one_lock_until_the_last_is_done(env, monkeypatch: pytest.MonkeyPatch) -> None:
    app, cert = env
    seen: list[object] = []
    original = app.users.verify

    def watched(name: str, password: str) -> Role | None:
        seen.append(app.security._user_locks.get(name))  # the lock the next attempt would take
        time.sleep(0.2)
        return original(name, password)

    monkeypatch.setattr(app.users, "verify", watched)
    results = await asyncio.gather(*(_login(app, cert, "user5", PASSWORD) for _ in range(3)))
    assert all(ok for _, ok in results)
    # While attempts overlapped, every one found the same lock: none was forgotten while another
    # still waited for it (a new attempt would then have run beside the waiting one).
    assert len(seen) == 3 and seen[0] is not None and all(x is seen[0] for x in seen)
    assert "user5" not in app.security._user_locks and "user5" not in app.security._lock_users


# --- issue 39 point 2: a delayed login is always answered before its connection's deadline -----------
WINDOW = 6.0  # [limits] activation_timeout of this server: the 30 s, scaled down


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def short(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[tuple[UacellServer, ClientCert]]:
    base = tmp_path_factory.mktemp("deadline")
    config = fast_config(base / "data")
    config.limits.activation_timeout = WINDOW
    app = await start_app(config)
    cert = ClientCert(base / "client")
    TrustList(PkiPaths.in_data_dir(app.data_dir)).trust(cert.der)
    app.users.add("ulla", Role.OPERATOR, PASSWORD)
    try:
        yield app, cert
    finally:
        await app.stop()


async def _timed_login(app: UacellServer, cert: ClientCert, password: str) -> tuple[float, str]:
    """Seconds from connecting to the answer, and the answer: "Good", a status code name, or the
    client's error when the connection was closed instead of answered."""
    start = time.monotonic()
    client = await secure_client(app, cert, user="ulla", password=password, connect=False)
    try:
        await client.connect()
    except ua.UaStatusCodeError as exc:
        return time.monotonic() - start, ua.StatusCode(exc.code).name
    except Exception as exc:  # "Connection is closed": dropped unanswered
        return time.monotonic() - start, f"dropped: {exc!r}"
    await client.disconnect()
    return time.monotonic() - start, "Good"


async def test_the_activation_deadline_is_the_configured_one(short) -> None:
    app, _ = short
    assert app.server.iserver.max_pending_activation_seconds == WINDOW


async def test_a_throttle_delay_as_long_as_the_deadline_is_answered_never_dropped(short) -> None:
    app, cert = short
    # The case: the delay reaches the activation deadline itself (30 s there, WINDOW here).
    app.security.throttle = LoginThrottle(base=WINDOW, cap=WINDOW, free=1, free_per_user=100)
    answers = [await _timed_login(app, cert, f"wrong-{i}") for i in range(6)]
    assert [code for _, code in answers] == ["BadUserAccessDenied"] * 6
    assert all(took < WINDOW for took, _ in answers), answers
    # The attempts that came too early for the delay were refused unchecked and not counted: fewer
    # failures counted than made.
    assert app.security.throttle._failures[("user", "ulla")][0] < 6


async def test_the_right_password_after_many_failures_is_slowed_then_checked_and_let_in(short) -> None:
    app, cert = short
    delay = 2.5  # the largest delay, well inside WINDOW less the margin
    app.security.throttle = throttle = LoginThrottle(base=1.0, cap=delay, free=1, free_per_user=100)
    # Six wrong passwords: free, then 1 s, 2 s, and three at the cap (2.5 s): the delay no longer grows.
    for i in range(6):
        took, code = await _timed_login(app, cert, f"wrong-{i}")
        assert code == "BadUserAccessDenied" and took < WINDOW
        await wait_until(lambda: throttle.wait_time("ulla", "127.0.0.1") < delay - 0.5, timeout=10)
    # The user who knows the password waits out the delay and gets in; never cut off unchecked.
    await wait_until(lambda: throttle.wait_time("ulla", "127.0.0.1") == 0.0, timeout=10)
    throttle.failed("ulla", "127.0.0.1")  # one more failure just now: the full delay applies
    assert throttle.wait_time("ulla", "127.0.0.1") > delay - 0.2
    took, code = await _timed_login(app, cert, PASSWORD)
    assert code == "Good"
    assert delay - 0.3 <= took < WINDOW


def _delayed(app: UacellServer, delay: float) -> LoginThrottle:
    """A throttle that makes ulla's next attempt wait ``delay`` seconds (two failures just now)."""
    app.security.throttle = throttle = LoginThrottle(base=delay, cap=delay, free=1, free_per_user=100)
    throttle.failed("ulla", "127.0.0.1")
    assert throttle.failed("ulla", "127.0.0.1") == pytest.approx(delay, abs=0.1)
    return throttle


async def _refused_at_once(client: Client, within: float, throttle: LoginThrottle) -> None:
    """The right password, answered Bad_UserAccessDenied within ``within`` s, unchecked and not counted."""
    start = time.monotonic()
    with pytest.raises(ua.UaStatusCodeError) as refused:
        await client.connect()
    assert refused.value.code == ua.StatusCodes.BadUserAccessDenied
    assert time.monotonic() - start < within
    assert throttle._failures[("user", "ulla")][0] == 2


async def test_a_client_that_waits_less_than_the_delay_is_answered_within_its_timeout_hint(short) -> None:
    app, cert = short
    throttle = _delayed(app, 3.0)
    client = Client(app.endpoint, timeout=2.0)  # its TimeoutHint: 2000 ms, less than the 3 s delay
    client.application_uri = cert.uri
    client.set_user("ulla")
    client.set_password(PASSWORD)
    await client.set_security(SecurityPolicyBasic256Sha256, str(cert.cert), str(cert.key))
    await _refused_at_once(client, 2.0, throttle)


async def test_a_delay_beyond_the_channels_lifetime_is_answered_before_the_channel_expires(short) -> None:
    app, cert = short
    throttle = _delayed(app, 4.0)
    client = await secure_client(app, cert, user="ulla", password=PASSWORD, connect=False)
    client.secure_channel_timeout = 3000  # the channel's token lives 3 s, less than the 4 s delay
    await _refused_at_once(client, 3.0, throttle)


async def test_a_max_delay_that_would_outlast_the_activation_deadline_is_refused(tmp_path) -> None:
    from uacell.config import load_config
    from uacell.core.errors import ConfigError

    path = tmp_path / "c.toml"
    path.write_text("[limits]\nlogin_max_delay = 30.0\n")  # the old default, equal to the deadline
    with pytest.raises(ConfigError, match=r"login_max_delay: must be at most 20 s"):
        load_config(path)
    path.write_text("[limits]\nactivation_timeout = 45.0\nlogin_max_delay = 30.0\n")
    assert load_config(path).limits.login_max_delay == 30.0
