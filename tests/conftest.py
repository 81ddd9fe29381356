"""Shared fixtures: free loopback ports, an in-process server, a `uacell serve` subprocess, node-opcua."""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import stream_sites
from helpers import free_port

from uacell.config import CACHE_DIR_ENV, Config
from uacell.core import logs
from uacell.core.companion import Binder, Companion
from uacell.core.early import event_loop_name
from uacell.host import ServerView
from uacell.server import UacellServer

# One address-space snapshot for the whole run (uacell.ua.snapshot): the first server writes it and
# every later one, in process or not, starts from it. tests/test_snapshot.py gives its servers their
# own cache directories to check building, staleness and damage.
_TEST_CACHE = tempfile.mkdtemp(prefix="uacell-test-cache-")
os.environ.setdefault(CACHE_DIR_ENV, _TEST_CACHE)
atexit.register(shutil.rmtree, _TEST_CACHE, True)

# A stream no test closed names the test and the code that opened it (tests/stream_sites.py).
stream_sites.install()


def pytest_asyncio_loop_factories(
    config: pytest.Config, item: pytest.Item
) -> dict[str, Callable[[], asyncio.AbstractEventLoop]]:
    """Tests run on the event loop `uacell serve` runs on: uvloop where it is installed, asyncio's own
    with ``UACELL_EVENT_LOOP=asyncio`` (core/early.py). The two differ where it matters (decision 105: a
    write on a closed transport, silent on asyncio's, raises on uvloop's)."""
    if event_loop_name() == "uvloop":
        import uvloop

        return {"uvloop": uvloop.new_event_loop}
    return {"asyncio": asyncio.new_event_loop}


@pytest.fixture(autouse=True)
def _fresh_repeat_counts() -> None:
    """The rate limit on repeated warnings (logs.REPEAT) is one per process: each test starts with
    no counts, so an earlier test's warnings in the same worker do not suppress or mark this one's."""
    logs.REPEAT.reset()


ROOT = Path(__file__).resolve().parents[1]
INTEROP = ROOT / "interop"
START_TIMEOUT = 120.0


@dataclass
class ServeProcess:
    proc: subprocess.Popen[str]
    endpoint: str
    data_dir: Path
    output: list[str]
    # the HMI's URL, set by the fixtures that start the process with web=True (wait_for_web)
    web: str = field(init=False, repr=False, compare=False)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        if self.proc.stdout is not None and not self.proc.stdout.closed:
            self.output.append(self.proc.stdout.read())
            self.proc.stdout.close()
        return rc


def start_serve(
    data_dir: Path,
    *extra: str,
    port: int | None = None,
    env: dict[str, str] | None = None,
    web: bool = False,
    host: str = "127.0.0.1",
    prefix: tuple[str, ...] = (),
    log_level: str = "WARNING",
) -> ServeProcess:
    """Run `uacell serve` on a free loopback port and wait for its listening line (what it printed
    until then is in ``output``).

    The web HMI is off unless ``web`` (then on a free port: pass ``--web-port`` in ``extra`` to choose).
    ``prefix`` runs the command through another (``ip netns exec NS``); ``host`` is where it listens.
    """
    port = port or free_port()
    if not web:
        extra = ("--no-web", *extra)
    elif "--web-port" not in extra:
        extra = ("--web-port", str(free_port()), *extra)
    cmd = [
        *prefix,
        sys.executable,
        "-m",
        "uacell",
        "--log-level",
        log_level,
        "serve",
        "--host",
        host,
        "--port",
        str(port),
        "--data-dir",
        str(data_dir),
        *extra,
    ]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, **(env or {})}
    )
    lines: list[str] = []
    deadline = time.monotonic() + START_TIMEOUT
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if line.startswith("uacell listening on "):
            return ServeProcess(proc, line.split(" on ", 1)[1].strip(), data_dir, lines)
    proc.kill()
    proc.wait()
    rest = proc.stdout.read() or ""
    proc.stdout.close()
    raise AssertionError("uacell serve did not start:\n" + "".join(lines) + rest)


def wait_for_web(sp: ServeProcess) -> str:
    """The HMI's URL once ``sp`` (started with ``web=True``) printed its "uacell web on" line."""
    while not any(line.startswith("uacell web on ") for line in sp.output):
        line = sp.proc.stdout.readline() if sp.proc.stdout else ""
        assert line, "".join(sp.output)
        sp.output.append(line)
    return next(line.split(" on ", 1)[1].strip() for line in sp.output if line.startswith("uacell web on "))


@pytest.fixture
def serve_process(tmp_path: Path) -> Iterator[ServeProcess]:
    """A real `uacell serve` subprocess on a free loopback port; stopped (SIGTERM) afterwards."""
    sp = start_serve(tmp_path / "data")
    yield sp
    sp.stop()


def fast_config(data_dir: Path) -> Config:
    """The demo cell on a free loopback port, with the simulators sped up for tests."""
    config = Config()
    config.server.port = free_port()
    config.server.data_dir = data_dir
    config.robot.time_scale = 20.0
    config.packml.acting_time = 0.05
    config.server.shutdown_delay = 0.0  # a stop never waits for a session a test left (test_shutdown.py)
    return config


async def start_app(
    config: Config,
    binders: list[Binder[ServerView]] | None = None,
    companions: Sequence[Companion[ServerView]] | None = None,
) -> UacellServer:
    """An in-process uacell server, set up and listening (on another free port if another test's
    listener took the chosen one meanwhile); ``companions``: those it serves (default: this build's)."""
    for attempt in range(3):
        server = UacellServer(config, binders=binders, companions=companions)
        await server.setup()
        try:
            await server.start()
            return server
        except OSError as exc:
            with contextlib.suppress(Exception):
                await server.stop()
            if exc.errno != errno.EADDRINUSE or attempt == 2:
                raise
            config.server.port = free_port()
    raise AssertionError("unreachable")


@contextlib.asynccontextmanager
async def serving(config: Config) -> AsyncIterator[tuple[UacellServer, Any]]:
    """``config`` served in-process with an asyncua client connected to it; both stopped after."""
    from asyncua import Client

    server = await start_app(config)
    try:
        # The client shares the event loop with the server it probes: its health probe gets 30 s, not
        # 1 s, so that a burst of work on a loaded machine (50 units resetting at once) does not drop it.
        async with Client(server.endpoint, timeout=30, watchdog_intervall=30.0) as client:
            yield server, client
    finally:
        await server.stop()


@pytest.fixture
async def app(tmp_path: Path) -> AsyncIterator[UacellServer]:
    """An in-process uacell server with the demo cell on a free loopback port."""
    server = await start_app(fast_config(tmp_path / "data"))
    try:
        yield server
    finally:
        await server.stop()


@pytest.fixture
async def client(app) -> AsyncIterator[Any]:
    """An asyncua client connected anonymously (operator on loopback) to ``app``."""
    from asyncua import Client

    # The client shares the server's event loop: asyncua's default 1 s watchdog read can miss its
    # answer while the loop builds the data type definitions on a loaded machine, and close a sound session.
    c = Client(app.endpoint, timeout=30, watchdog_intervall=30.0)
    await c.connect()
    await c.load_data_type_definitions()
    try:
        yield c
    finally:
        await c.disconnect()


def run_node(script: str, endpoint: str, *args: str, timeout: float = 120.0) -> dict[str, Any]:
    """Run interop/<script> with node-opcua-client; it prints one JSON object as its last JSON line
    (node-opcua may print a log line of its own after it, e.g. a warning about RSA PKCS#1 v1.5)."""
    proc = subprocess.run(
        ["node", str(INTEROP / script), endpoint, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=INTEROP,
        check=False,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise AssertionError(f"{script} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return json.loads(lines[-1])


class NodeServer:
    """A server script of interop/ (node-opcua), running once it printed "listening"; stderr goes to ``log``."""

    def __init__(self, script: str, args: list[str], log: Path) -> None:
        with log.open("w") as errors:
            self.proc = subprocess.Popen(
                ["node", str(INTEROP / script), *args], cwd=INTEROP, stdout=subprocess.PIPE, stderr=errors, text=True
            )
        assert self.proc.stdout is not None
        output = []
        for line in self.proc.stdout:  # until "listening", or the end when it failed
            if line.strip() == "listening":
                return
            output.append(line)
        self.stop()
        raise AssertionError(f"{script} did not start: {''.join(output)}{log.read_text()}")

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Any]:
    """A mosquitto of the test's own on a free loopback port (tests/mqtt_broker.py), stopped after."""
    from mqtt_broker import running_broker

    with running_broker(tmp_path / "broker") as b:
        yield b
