"""A real MQTT broker for tests: Debian's mosquitto on a free loopback port (``make setup`` installs
it), and a subscriber that collects what arrives. Every broker a test starts is stopped by it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from helpers import free_port, wait_until

MOSQUITTO = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
needs_mosquitto = pytest.mark.skipif(
    MOSQUITTO is None, reason="mosquitto is not installed (make setup installs it as root: apt-get install mosquitto)"
)


@dataclass
class TlsFiles:
    ca: Path
    cert: Path
    key: Path


class Broker:
    """mosquitto with a configuration of its own: anonymous, or with one user and password, and TLS."""

    def __init__(
        self,
        workdir: Path,
        *,
        users: dict[str, str] | None = None,
        tls: TlsFiles | None = None,
        port: int | None = None,
    ) -> None:
        self.workdir = workdir
        self.port = port or free_port()
        self.users = users
        self.tls = tls
        self.process: subprocess.Popen[bytes] | None = None
        workdir.mkdir(parents=True, exist_ok=True)

    @property
    def url(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://127.0.0.1:{self.port}"

    def _config(self) -> Path:
        lines = [f"listener {self.port} 127.0.0.1", "persistence false", "user root", "log_type error"]
        lines.append("log_type warning")
        if self.users:
            passwd = self.workdir / "passwd"
            passwd.write_text("")
            for user, password in self.users.items():
                subprocess.run(["mosquitto_passwd", "-b", str(passwd), user, password], check=True)
            lines += ["allow_anonymous false", f"password_file {passwd}"]
        else:
            lines.append("allow_anonymous true")
        if self.tls:
            lines += [f"cafile {self.tls.ca}", f"certfile {self.tls.cert}", f"keyfile {self.tls.key}"]
        conf = self.workdir / "mosquitto.conf"
        conf.write_text("\n".join(lines) + "\n")
        return conf

    def start(self) -> None:
        assert MOSQUITTO is not None
        log = open(self.workdir / "mosquitto.log", "ab")
        self.process = subprocess.Popen([MOSQUITTO, "-c", str(self._config())], stdout=log, stderr=log)
        log.close()
        deadline = time.monotonic() + 15
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {(self.workdir / 'mosquitto.log').read_text()}")
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port), 0.2):
                return
            assert time.monotonic() < deadline, "mosquitto did not listen"
            time.sleep(0.02)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            os.kill(self.process.pid, signal.SIGCONT)  # a broker a test left stopped takes SIGTERM only then
            self.process.terminate()
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)
        self.process = None

    def kill(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.wait(5)
        self.process = None


@dataclass
class Received:
    topic: str
    body: Any  # the JSON payload, or None when not JSON (or empty)
    retain: bool
    raw: bytes = b""  # the payload as it arrived


@dataclass
class Subscriber:
    """Everything published under ``topic_filter`` since it subscribed, in arrival order."""

    messages: list[Received] = field(default_factory=list)

    def data(self, writer_suffix: str = "") -> list[dict[str, Any]]:
        """The DataSetMessages on data topics (ending with ``writer_suffix``), in order."""
        return [
            m
            for r in self.messages
            if "/json/data/" in r.topic and r.topic.endswith(writer_suffix) and isinstance(r.body, dict)
            for m in r.body.get("Messages", [])
        ]

    def on(self, predicate: Callable[[Received], bool]) -> list[Received]:
        return [r for r in self.messages if predicate(r)]

    async def wait_for(self, predicate: Callable[[Received], bool], timeout: float = 30.0) -> Received:
        await wait_until(lambda: any(predicate(r) for r in self.messages), timeout=timeout, step=0.01)
        return next(r for r in self.messages if predicate(r))


@contextlib.asynccontextmanager
async def subscribed(
    broker: Broker, topic_filter: str = "#", *, username: str | None = None, password: str | None = None, **tls: Any
) -> AsyncIterator[Subscriber]:
    """A subscriber on ``broker`` collecting ``topic_filter`` (retained messages included)."""
    sub = Subscriber()
    ready = asyncio.Event()

    async def run() -> None:
        async with aiomqtt.Client("127.0.0.1", broker.port, username=username, password=password, **tls) as c:
            await c.subscribe(topic_filter, qos=1)
            ready.set()
            async for message in c.messages:
                payload = message.payload
                body = None
                if isinstance(payload, bytes | bytearray) and payload:
                    with contextlib.suppress(ValueError):
                        body = json.loads(payload)
                raw = bytes(payload) if isinstance(payload, bytes | bytearray) else b""
                sub.messages.append(Received(str(message.topic), body, bool(message.retain), raw))

    task = asyncio.ensure_future(run())
    try:
        await asyncio.wait_for(asyncio.shield(_first(ready, task)), 15)
        yield sub
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await task


async def _first(ready: asyncio.Event, task: asyncio.Future[None]) -> None:
    waiter = asyncio.ensure_future(ready.wait())
    either: set[asyncio.Future[Any]] = {waiter, task}
    await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
    if task.done():
        task.result()
        raise RuntimeError("the subscriber stopped before subscribing")


def make_tls(directory: Path) -> TlsFiles:
    """A CA and a broker certificate it signed, for 127.0.0.1 (PEM files in ``directory``)."""
    import datetime as dt
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    directory.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now(dt.UTC)

    def name(cn: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (
        x509.CertificateBuilder()
        .subject_name(name("uacell test CA"))
        .issuer_name(name("uacell test CA"))
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(name("127.0.0.1"))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    files = TlsFiles(directory / "ca.pem", directory / "broker.pem", directory / "broker.key")
    files.ca.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    files.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    files.key.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    return files


@contextlib.contextmanager
def running_broker(workdir: Path, **options: Any) -> Iterator[Broker]:
    """A started ``Broker`` (options as its constructor's), stopped after (also on failure)."""
    b = Broker(workdir, **options)
    b.start()
    try:
        yield b
    finally:
        b.stop()
