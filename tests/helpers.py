"""What several test files share: the models' state tables, clocks, waits on conditions, free ports.

Import as ``from helpers import ...`` (pytest puts ``tests/`` on the path).
"""

from __future__ import annotations

import asyncio
import functools
import os
import random
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, cast

from asyncua import Client, ua

from uacell.catalog import companions
from uacell.core.companion import models_of
from uacell.di.locking import LockManager
from uacell.di.locks import LOCK_SERVICE
from uacell.models import ModelFile, StateTables, official_models
from uacell.packml import PackMLTables
from uacell.robotics import RobotCell, RoboticsTables
from uacell.robotics.binding import CONTROLLERS, RoboticsBinding
from uacell.robotics.sim import SimulatedRobot
from uacell.server import UacellServer
from uacell.ua.toolkit import EventEmitter


@functools.cache
def official() -> tuple[ModelFile, ...]:
    """This build's official models: those of the catalog's companions, in load order, as the server
    (``UacellServer.models``) and the CLI get them."""
    return official_models(models_of(companions()))


@functools.cache
def robotics_tables() -> RoboticsTables:
    """The Robotics tables from the default models directory (the cache ``make setup`` fills)."""
    return RoboticsTables.load(StateTables(official()))


@functools.cache
def packml_tables() -> PackMLTables:
    return PackMLTables.load(StateTables(official()))


def _ephemeral_ports() -> range:
    """The range the kernel gives outgoing connections their local port from."""
    try:
        low, high = (int(x) for x in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    except (OSError, ValueError):
        low, high = 32768, 60999
    return range(low, high + 1)


_EPHEMERAL = _ephemeral_ports()


def _own_ports() -> range:
    """The listening ports this process may hand out: below the ephemeral range, and under pytest-xdist
    a slice of their own per worker, so that two workers never pick the same port."""
    ports = range(10000, min(_EPHEMERAL.start, 32768))
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or "1")
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if count <= 1 or not worker.startswith("gw") or not worker[2:].isdigit():
        return ports
    size = len(ports) // count
    start = ports.start + (int(worker[2:]) % count) * size
    return range(start, start + size)


_OWN_PORTS = _own_ports()
_next_port = random.Random().randrange(len(_OWN_PORTS))


def free_port() -> int:
    """A TCP port nobody listens on at 127.0.0.1 right now, and one this process has not handed out
    before (until its slice wraps round): a test that asks twice gets two ports.

    The port is outside the ephemeral range: a port the kernel hands out (bind to 0) can be taken by any
    outgoing connection of a parallel test before the server binds it; one below that range can only be
    taken by another listener, and under pytest-xdist each worker takes from its own slice."""
    global _next_port
    for _ in range(min(200, len(_OWN_PORTS))):
        port = _OWN_PORTS[_next_port % len(_OWN_PORTS)]
        _next_port += 1
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # the range is crowded: any free one
        s.bind(("127.0.0.1", 0))
        found: int = s.getsockname()[1]
        return found


class FakeClock:
    """A monotonic clock tests advance by hand: ``clock()`` reads it, ``clock.advance(s)`` moves it."""

    def __init__(self, start: float = 1000.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


async def wait_until(predicate: Callable[[], bool], timeout: float = 30.0, step: float = 0.0005) -> None:
    """Wait until ``predicate()`` holds (checked every ``step`` s); fail after ``timeout`` s."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not predicate():
        assert loop.time() < deadline, "condition not reached"
        await asyncio.sleep(step)


CONTROLLER1 = "Robot1.Controllers.Controller1"


def robot_binding(app: UacellServer, path: str = CONTROLLER1) -> RoboticsBinding:
    """The Robotics binding of the controller at ``path`` in the demo cell."""
    return app.registry(CONTROLLERS)[path]


def robot_cell(app: UacellServer, path: str = CONTROLLER1) -> RobotCell:
    """The pure model of the controller at ``path``."""
    return robot_binding(app, path).cell


def simulated_robot(app: UacellServer, path: str = CONTROLLER1) -> SimulatedRobot:
    """The equipment of the controller at ``path`` where it is the simulator (the demo cell's are)."""
    return cast(SimulatedRobot, robot_cell(app, path).equipment)


def lock_manager(app: UacellServer) -> LockManager:
    return app.registry(LOCK_SERVICE)[""].manager


class VirtualTime:
    """Injected time for simulators: ``sleep(s)`` moves ``clock()`` on by ``s`` at once, then yields.

    One sleeper at a time sees exact time; concurrent sleepers each move the shared clock on.
    """

    def __init__(self, start: float = 0.0) -> None:
        self.now = start
        self.slept = 0.0

    def clock(self) -> float:
        return self.now

    async def sleep(self, seconds: float) -> None:
        self.now += seconds
        self.slept += seconds
        await asyncio.sleep(0)


async def raw_call(client: Client, obj: ua.NodeId, method: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
    """Call ``method`` on ``obj`` and return the CallMethodResult as it arrived (StatusCode, input
    argument results, outputs); ``Node.call_method`` would raise on a Bad status instead."""
    req = ua.CallMethodRequest(ObjectId=obj, MethodId=method, InputArguments=list(args))
    (res,) = await client.uaclient.call([req])
    return res


async def call_path(client: Client, obj: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    """``raw_call`` of ``obj.method`` named by their cell-namespace paths (``"Filler1"``, ``"SetMachSpeed"``)."""
    ns = await client.get_namespace_index("urn:uacell:cell")
    return await raw_call(client, ua.NodeId(obj, ns), ua.NodeId(f"{obj}.{method}", ns), *args)


def server_value(app: UacellServer, nodeid: ua.NodeId) -> Any:
    """The Value of ``nodeid`` as the server holds it (no client round trip)."""
    return app.server.iserver.aspace.read_attribute_value(nodeid, ua.AttributeIds.Value).Value.Value


class EventSink(Protocol):
    events: list[Any]

    async def wait_for(self, match: Callable[[Any], bool], timeout: float = ...) -> Any: ...


async def fire_marker(app: UacellServer, source: ua.NodeId, marker: str) -> None:
    """Settle the server, then fire a TransitionEvent from ``source`` whose Message, Transition,
    FromState and ToState are all ``marker``: once a subscriber has it, it has everything before it."""
    await app.settle()
    text = (ua.LocalizedText(marker), ua.VariantType.LocalizedText)
    emitter = await EventEmitter.create(app.server, ua.ObjectIds.TransitionEventType, source)
    await emitter.fire(
        (source,),
        {"Transition": text, "FromState": text, "ToState": text},
        EventId=uuid.uuid4().bytes,
        Message=ua.LocalizedText(marker),
        SourceNode=source,
        Severity=1,
    )


async def delivered(app: UacellServer, sink: EventSink, *sources: ua.NodeId) -> None:
    """Wait until ``sink`` holds every TransitionEvent the server produced so far from ``sources``.

    The server settles (every model change published, every event triggered), then fires a marker
    event from each source; events of a subscription arrive in order, so once the markers are in,
    nothing produced before them is still on its way. The markers are then dropped from ``sink``.
    """
    marker = f"uacell-test-marker {uuid.uuid4().hex}"
    for source in sources:
        await fire_marker(app, source, marker)

    def is_marker(event: Any) -> bool:
        return getattr(getattr(event, "Message", None), "Text", None) == marker

    await sink.wait_for(lambda _e: sum(1 for e in sink.events if is_marker(e)) >= len(sources))
    sink.events[:] = [e for e in sink.events if not is_marker(e)]


class Collector:
    """Collects what one subscription delivers (events, and data changes as (node, value));
    ``wait_for`` returns the first item that matches, waiting for more as they arrive."""

    timeout = 30.0

    def __init__(self) -> None:
        self.events: list[Any] = []
        self.changed = asyncio.Event()

    def event_notification(self, event: Any) -> None:
        self.events.append(event)
        self.changed.set()

    def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
        self.events.append((node, value))
        self.changed.set()

    async def wait_for(self, match: Callable[[Any], bool], timeout: float | None = None) -> Any:
        async with asyncio.timeout(self.timeout if timeout is None else timeout):
            while True:
                for e in self.events:
                    if match(e):
                        return e
                self.changed.clear()
                await self.changed.wait()

    def clear(self) -> None:
        self.events.clear()


class CellClient:
    """An asyncua client session that names the cell's instances by their NodeId paths (tests may;
    the HMI may not): ``async with CellClient(endpoint) as c: await c.node("Filler1...").read_value()``."""

    def __init__(
        self, endpoint: str, uri: str, user: str | None = None, password: str | None = None, **options: Any
    ) -> None:
        self.client = Client(endpoint, timeout=30, **options)
        self.client.application_uri = uri
        if user:
            self.client.set_user(user)
            self.client.set_password(password or "")

    async def __aenter__(self) -> Any:
        await self.client.connect()
        self.ns = await self.client.get_namespace_index("urn:uacell:cell")
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.client.disconnect()

    def node(self, path: str) -> Any:
        return self.client.get_node(ua.NodeId(path, self.ns))


async def config_check_connect(path: Path) -> subprocess.CompletedProcess[str]:
    """``uacell config check --connect PATH`` with this checkout's source, off the event loop."""
    src = str(Path(__file__).resolve().parents[1] / "src")
    return await asyncio.to_thread(
        subprocess.run,
        [sys.executable, "-m", "uacell", "config", "check", "--connect", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": src},
    )


# -- PackML units in a PLC (the gateway tests) ---------------------------------------------------


async def cell_state(client: Client, machine: str) -> str | None:
    ns = await client.get_namespace_index("urn:uacell:cell")
    dv = await client.get_node(ua.NodeId(f"{machine}.CurrentState", ns)).read_data_value(raise_on_bad_status=False)
    return dv.Value.Value.Text if dv.StatusCode.is_good() else None


async def until(read: Any, expected: Any, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while (got := await read()) != expected:
        assert time.monotonic() < deadline, f"{got!r}, waited for {expected!r}"
        await asyncio.sleep(0.02)


async def cell_read(client: Client, path: str) -> Any:
    ns = await client.get_namespace_index("urn:uacell:cell")
    return await client.get_node(ua.NodeId(path, ns)).read_value()


async def cell_executable(client: Client, method: str) -> bool:
    """The Executable attribute of the cell's method ``method`` (a path such as ``Capper....Reset``)."""
    ns = await client.get_namespace_index("urn:uacell:cell")
    dv = await client.get_node(ua.NodeId(method, ns)).read_attribute(ua.AttributeIds.Executable)
    return bool(dv.Value.Value)


async def cell_status(client: Client, path: str) -> str:
    """The status code's name a Read of the cell's variable ``path`` answers."""
    ns = await client.get_namespace_index("urn:uacell:cell")
    return str((await client.get_node(ua.NodeId(path, ns)).read_data_value(raise_on_bad_status=False)).StatusCode.name)


def packml_params(*pairs: tuple[int, float]) -> ua.Variant:
    return ua.Variant(
        [ua.PackMLDescriptorDataType(ID=i, Name=f"P{i}", Unit=ua.EUInformation(), Value=v) for i, v in pairs],
        ua.VariantType.ExtensionObject,
        is_array=True,
    )


def models_copy(where: Path) -> str:
    """A models directory with links to the official NodeSet files and nothing else (no models'
    snapshot beside them): a server given it builds the models from the files."""
    from uacell.models.source import locate_models

    where.mkdir(parents=True, exist_ok=True)
    for path in locate_models(official()).values():
        (where / path.name).symlink_to(path.resolve())
    return str(where)


def first_start_source() -> str:
    """Where a first start with the default models directory takes the models from."""
    from uacell.ua.nodesets import models_snapshot_path

    return "models snapshot" if models_snapshot_path(official(), None).exists() else "nodesets"


async def session_on_new_channel(client: Client, token: ua.NodeId, nonce: bytes | None) -> Client:
    """``client`` (configured, not connected) opens a new connection and secure channel and activates the
    existing session of AuthenticationToken ``token`` on it (OPC 10000-4 5.6.3.1: a session moved to a new
    channel, as a client reconnecting after a lost connection does), with asyncua's own client steps;
    ``nonce`` is the last one the server gave the session. Raises what the server answered."""
    await client.connect_socket()
    try:
        await client.send_hello()
        await client.open_secure_channel()
        client.uaclient.protocol.authentication_token = token
        client._server_nonce = nonce
        await client.activate_session()
    except BaseException:
        client.disconnect_socket()
        raise
    return client


async def secure_client(endpoint: str, directory: Path, cert: Any, key: Any, uri: str) -> Client:
    """An asyncua client (not connected yet) over Basic256Sha256 SignAndEncrypt with ``cert`` (a
    cryptography certificate) and ``key`` (its RSA key) as application ``uri``; the files go to ``directory``."""
    from asyncua.crypto import security_policies
    from cryptography.hazmat.primitives import serialization

    (directory / "c.der").write_bytes(cert.public_bytes(serialization.Encoding.DER))
    (directory / "k.pem").write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    client = Client(endpoint, timeout=20)
    client.application_uri = uri
    await client.set_security(
        security_policies.SecurityPolicyBasic256Sha256,
        str(directory / "c.der"),
        str(directory / "k.pem"),
        mode=ua.MessageSecurityMode.SignAndEncrypt,
    )
    return client


def add_user(data_dir: Path, *args: str, password: str | None = None, command: str = "add") -> None:
    """``uacell user add ARGS`` (or another ``command``) on ``data_dir``, as an administrator runs it
    (``password`` on stdin)."""
    extra = ["--password-stdin"] if password is not None else []
    added = subprocess.run(
        [sys.executable, "-m", "uacell", "user", "--data-dir", str(data_dir), command, *args, *extra],
        input=f"{password}\n" if password is not None else "",
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert added.returncode == 0, added.stderr
